/*
 * avr_bridge: the psmini-leds sketch's compiled ELF on an emulated ATmega328P (simavr), wired like a Nano.
 *
 * Written for psmini's tests (MIT, like psmini). It is compiled at test time and linked against Debian's
 * libsimavr (GPL-3); psmini itself never links or ships it.
 *
 *   avr_bridge FIRMWARE.elf [--baud 115200] [--boot-ms 0] [--speed 1.0]
 *
 * - The UART is served on a pseudo-terminal (its path is the first line on stdout: "PTY /dev/pts/N"). The host
 *   opens it like a USB serial port; opening it resets the AVR, as DTR resets a Nano (the "bootloader" then
 *   holds it in reset for --boot-ms of emulated time). Bytes from the host are clocked into the AVR's receiver at
 *   --baud, 8N1 (10 bit times a byte), as the USB-serial chip of a Nano does, however fast the host writes.
 * - The emulated clock never runs ahead of the wall clock (times --speed): timeouts of the host stay meaningful.
 * - Events go to stdout, one line each, stamped with the emulated cycle (16 MHz) since the bridge started:
 *     P <cycle> <mask>           the LED pins D2..D9 (bit i = LED i = D(2+i)) after a change
 *     U <cycle> <port><bit> <0|1>  any other port pin written (PB2..PB5, PC0..PC5): none should ever be
 *     R <cycle> <hex byte>       a byte fully received by the AVR's UART (its stop bit ended)
 *     T <cycle> <hex byte>       a byte the AVR's UART started to send
 *     O <cycle>                  the host opened the port (the AVR was reset)
 *     C <cycle>                  the host closed the port
 *     S <cycle>                  the sketch starts running (reset released after the boot delay)
 *     K <cycle> <pending>        a clock tick (every 10 ms emulated); pending: host bytes not yet clocked in
 *     A <cycle> <pending>        the answer to "t" on stdin (after every earlier event)
 *     Q <cycle>                  the bridge quits
 * - stdin: "t" (answer with an A line), "q" or end of file (quit).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <avr_ioport.h>
#include <avr_uart.h>
#include <sim_avr.h>
#include <sim_elf.h>
#include <sim_irq.h>
#include <sim_io.h>
#include <sim_cycle_timers.h>

#define FREQUENCY 16000000ULL
#define HOST_BUFFER (1 << 20)
#define SLICE_CYCLES 1600ULL     /* poll the pty and stdin every 100 us of emulated time */
#define TICK_CYCLES 160000ULL    /* a K line every 10 ms */

static avr_t *avr;
static int master = -1;
static unsigned baud = 115200;
static double speed = 1.0;
static uint64_t boot_cycles = 0;

/* emulated time: cycles of this AVR run plus everything before its last reset */
static uint64_t base_cycles = 0;
static uint64_t held_until = 0;   /* emulated cycle until which the AVR is held in reset (the bootloader) */
static int held = 0;

static uint8_t host[HOST_BUFFER];
static size_t host_head = 0, host_tail = 0;
static uint8_t pins = 0;
static int host_open = 0;
static uint64_t next_byte_cycle = 0; /* when the next host byte may finish on the wire, emulated cycles */
static uint64_t byte_index = 0;      /* of the current wire run, for exact fractional byte times */
static uint64_t run_start = 0;

static avr_uart_t *uart;
static avr_irq_t *uart_input;

/* simavr 1.6 counts a parity bit in every frame (11 bit times for 8N1, 10% slow); the ATmega328P sends and
 * receives 8N1 frames of 10 bit times. Correct its byte time whenever the sketch has (re)configured the UART. */
static avr_cycle_count_t corrected_byte_time = 0;

static void correct_frame_time(void) {
    if (uart->cycles_per_byte == corrected_byte_time) {
        return;
    }
    uint8_t ucsrc = avr->data[uart->r_ucsrc];
    int parity = (ucsrc >> 4) & 3;
    if (!parity && uart->cycles_per_byte % 11 == 0 && uart->cycles_per_byte > 0) {
        uart->cycles_per_byte = uart->cycles_per_byte / 11 * 10;
    }
    corrected_byte_time = uart->cycles_per_byte;
}

static uint64_t now_cycles(void) { return base_cycles + (held ? 0 : avr->cycle); }

static uint64_t wall_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000ULL + (uint64_t)t.tv_nsec;
}

static void pin_changed(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    uint8_t bit = (uint8_t)(uintptr_t)param;
    uint8_t next = value ? (uint8_t)(pins | (1u << bit)) : (uint8_t)(pins & ~(1u << bit));
    if (next != pins) {
        pins = next;
        printf("P %llu %u\n", (unsigned long long)now_cycles(), pins);
    }
}

static void other_pin_changed(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    uintptr_t pin = (uintptr_t)param; /* port letter << 8 | bit */
    printf("U %llu %c%u %u\n", (unsigned long long)now_cycles(), (char)(pin >> 8), (unsigned)(pin & 0xFF),
           value ? 1u : 0u);
}

static void uart_output(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    uint8_t byte = (uint8_t)value;
    printf("T %llu %02x\n", (unsigned long long)now_cycles(), byte);
    if (host_open && master >= 0) {
        ssize_t written = write(master, &byte, 1);
        (void)written; /* a host that closed its end loses the byte, as with an unplugged cable */
    }
}

/* 10 bit times per byte at the host's baud rate, in 16 MHz cycles, exact over a run of bytes */
static uint64_t wire_time(uint64_t index) { return index * FREQUENCY * 10ULL / baud; }

static void feed_host_bytes(void) {
    /* called between instructions: deliver every byte whose stop bit has ended by now */
    if (held) {
        return;
    }
    uint64_t now = now_cycles();
    while (host_head != host_tail && now >= next_byte_cycle) {
        uint8_t byte = host[host_head];
        host_head = (host_head + 1) % HOST_BUFFER;
        avr_raise_irq(uart_input, byte);
        printf("R %llu %02x\n", (unsigned long long)next_byte_cycle, byte);
        byte_index++;
        next_byte_cycle = run_start + wire_time(byte_index);
    }
}

static void start_wire_run(void) {
    /* the first byte after an idle line starts now and ends one byte time later */
    run_start = now_cycles();
    byte_index = 1;
    next_byte_cycle = run_start + wire_time(1);
}

static void reset_board(void) {
    uint64_t total = now_cycles();
    avr_reset(avr);
    if (pins) {
        pins = 0; /* the pins float at reset: the LEDs go out */
        printf("P %llu %u\n", (unsigned long long)total, pins);
    }
    host_head = host_tail = 0; /* nothing the host sent before it opened the port is delivered */
    held = boot_cycles > 0;
    held_until = total + boot_cycles;
    base_cycles = held ? total : total - avr->cycle;
}

static void release_if_booted(void) {
    if (held && base_cycles >= held_until) {
        held = 0;
        base_cycles -= avr->cycle;
        printf("S %llu\n", (unsigned long long)now_cycles());
    }
}

static void host_io(void) {
    struct pollfd fds[2] = {{master, POLLIN, 0}, {0, POLLIN, 0}};
    if (poll(fds, 2, 0) < 0) {
        return;
    }
    int hung_up = (fds[0].revents & POLLHUP) != 0;
    if (hung_up && host_open) {
        host_open = 0;
        printf("C %llu\n", (unsigned long long)now_cycles());
    } else if (!hung_up && !host_open) {
        host_open = 1;
        reset_board();
        printf("O %llu\n", (unsigned long long)now_cycles());
        if (!held) {
            printf("S %llu\n", (unsigned long long)now_cycles());
        }
    }
    if (!hung_up && (fds[0].revents & POLLIN)) {
        uint8_t chunk[4096];
        ssize_t count = read(master, chunk, sizeof chunk);
        for (ssize_t i = 0; i < count; i++) {
            size_t next = (host_tail + 1) % HOST_BUFFER;
            if (next == host_head) {
                break; /* a megabyte pending: the host is far past any sane flood */
            }
            if (host_head == host_tail && now_cycles() >= next_byte_cycle) {
                start_wire_run();
            }
            host[host_tail] = chunk[i];
            host_tail = next;
        }
    }
    if (fds[1].revents & (POLLIN | POLLHUP)) {
        char command[64];
        if (fgets(command, sizeof command, stdin) == NULL || command[0] == 'q') {
            printf("Q %llu\n", (unsigned long long)now_cycles());
            fflush(stdout);
            exit(0);
        }
        if (command[0] == 't') {
            size_t pending = (host_tail + HOST_BUFFER - host_head) % HOST_BUFFER;
            printf("A %llu %zu\n", (unsigned long long)now_cycles(), pending);
        }
    }
    fflush(stdout);
}

static void keep_to_wall_clock(uint64_t wall_start) {
    if (speed <= 0) {
        return; /* free-running */
    }
    uint64_t emulated_ns = now_cycles() * 1000ULL / (FREQUENCY / 1000000ULL);
    uint64_t allowed_ns = (uint64_t)((double)(wall_ns() - wall_start) * speed);
    if (emulated_ns > allowed_ns + 200000ULL) {
        uint64_t ahead = emulated_ns - allowed_ns;
        struct timespec pause = {(time_t)(ahead / 1000000000ULL), (long)(ahead % 1000000000ULL)};
        nanosleep(&pause, NULL);
    }
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s FIRMWARE.elf [--baud N] [--boot-ms N] [--speed X]\n", argv[0]);
        return 2;
    }
    for (int i = 2; i + 1 < argc; i += 2) {
        if (strcmp(argv[i], "--baud") == 0) {
            baud = (unsigned)strtoul(argv[i + 1], NULL, 10);
        } else if (strcmp(argv[i], "--boot-ms") == 0) {
            boot_cycles = strtoull(argv[i + 1], NULL, 10) * (FREQUENCY / 1000ULL);
        } else if (strcmp(argv[i], "--speed") == 0) {
            speed = strtod(argv[i + 1], NULL);
        } else {
            fprintf(stderr, "avr_bridge: unknown option %s\n", argv[i]);
            return 2;
        }
    }
    if (baud == 0) {
        fprintf(stderr, "avr_bridge: --baud must be positive\n");
        return 2;
    }
    elf_firmware_t firmware;
    memset(&firmware, 0, sizeof firmware);
    if (elf_read_firmware(argv[1], &firmware) != 0) {
        fprintf(stderr, "avr_bridge: cannot read the firmware %s\n", argv[1]);
        return 1;
    }
    strcpy(firmware.mmcu, "atmega328p");
    firmware.frequency = (uint32_t)FREQUENCY;
    avr = avr_make_mcu_by_name(firmware.mmcu);
    if (avr == NULL || avr_init(avr) != 0) {
        fprintf(stderr, "avr_bridge: simavr has no atmega328p\n");
        return 1;
    }
    avr->log = 0;
    avr_load_firmware(avr, &firmware);

    /* LED i on D(2+i): D2..D7 are PD2..PD7, D8 and D9 are PB0 and PB1 */
    for (uint8_t led = 0; led < 8; led++) {
        char port = led < 6 ? 'D' : 'B';
        int bit = led < 6 ? led + 2 : led - 6;
        avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), bit), pin_changed,
                                (void *)(uintptr_t)led);
    }
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_output, NULL);
    /* every other port pin (PD0 and PD1 are the UART's RX and TX), so that a stray pin shows */
    const char *others[] = {"B2345", "C012345"};
    for (int p = 0; p < 2; p++) {
        char port = others[p][0];
        for (const char *bit = others[p] + 1; *bit; bit++) {
            uintptr_t pin = ((uintptr_t)(unsigned char)port << 8) | (uintptr_t)(*bit - '0');
            avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), *bit - '0'), other_pin_changed,
                                    (void *)pin);
        }
    }
    for (avr_io_t *io = avr->io_port; io != NULL; io = io->next) {
        if (io->kind != NULL && strcmp(io->kind, "uart") == 0) {
            uart = (avr_uart_t *)io;
        }
    }
    uart_input = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    if (uart == NULL) {
        fprintf(stderr, "avr_bridge: simavr's atmega328p has no UART\n");
        return 1;
    }

    int slave = -1;
    if (openpty(&master, &slave, NULL, NULL, NULL) != 0) {
        perror("avr_bridge: openpty");
        return 1;
    }
    struct termios raw;
    tcgetattr(slave, &raw);
    cfmakeraw(&raw);
    tcsetattr(slave, TCSANOW, &raw);
    printf("PTY %s\n", ttyname(slave));
    close(slave); /* held open here, it would hide the host's open and close from the master */
    fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);
    fflush(stdout);

    /* the board is powered (and runs its sketch) before any host opens the port */
    printf("S 0\n");
    uint64_t wall_start = wall_ns();
    uint64_t next_slice = 0, next_tick = TICK_CYCLES;
    for (;;) {
        if (held) {
            base_cycles += SLICE_CYCLES; /* the bootloader's wait: time passes, the sketch does not run */
            release_if_booted();
        } else {
            uint64_t stop = now_cycles() + SLICE_CYCLES;
            while (now_cycles() < stop) {
                int state = avr_run(avr);
                if (state == cpu_Done || state == cpu_Crashed) {
                    printf("X %llu %d\n", (unsigned long long)now_cycles(), state);
                    fflush(stdout);
                    return 3;
                }
                correct_frame_time();
                feed_host_bytes();
            }
        }
        if (now_cycles() >= next_slice) {
            next_slice = now_cycles() + SLICE_CYCLES;
            host_io();
            keep_to_wall_clock(wall_start);
        }
        if (now_cycles() >= next_tick) {
            next_tick += TICK_CYCLES;
            size_t pending = (host_tail + HOST_BUFFER - host_head) % HOST_BUFFER;
            printf("K %llu %zu\n", (unsigned long long)now_cycles(), pending);
        }
    }
}
