// psmini-leds: the LED controller of the psmini photometric-stereo rig (Arduino Nano, ATmega328P).
//
// Eight LEDs, one per digital pin D2..D9, each through its own series resistor (or a transistor stage),
// switched on a software trigger from the host over USB serial at 115200 baud, 8N1.
// The protocol is specified in docs/rig-protocol.md; in short:
//
//   after reset   READY psmini-leds 1.0.0 leds=8 wdt=2000
//   PING          OK PING
//   ID?           OK ID psmini-leds 1.0.0 leds=8 wdt=2000
//   ON i          OK ON i         exactly LED i lit (0 <= i < 8), the others off
//   ALL           OK ALL          every LED lit (focus sweeps, alignment)
//   OFF           OK OFF          every LED off
//   STATE?        OK STATE on=<i|-|all> wdt=<ms> trips=<n>
//   WDT ms        OK WDT ms       watchdog timeout, 100..60000 ms
//   anything else ERR <code> <message>
//
// Every command line gets exactly one reply line; lines end with '\n' ('\r' is ignored). Nothing else is
// ever sent, so the host can pair replies with commands.
//
// Design rules (FIELD_NOTES, "Rig"):
// - The parser never blocks: loop() takes the bytes that have arrived and returns (no Serial.readString(),
//   whose 1 s timeout would stall every command).
// - LEDs are driven at DC with digitalWrite. analogWrite() would run PWM at 490/980 Hz, which beats with
//   short camera exposures; it is never used.
// - A watchdog switches the LEDs off when no complete line has arrived for wdt ms (a crashed host must not
//   leave an LED burning). It is silent: it changes state and counts a trip, it sends no line.

#include <Arduino.h>
#include <stdlib.h>
#include <string.h>

static const char FIRMWARE_NAME[] = "psmini-leds";
static const char FIRMWARE_VERSION[] = "1.0.0";
static const uint8_t LED_PINS[] = {2, 3, 4, 5, 6, 7, 8, 9};
static const uint8_t LED_COUNT = sizeof(LED_PINS) / sizeof(LED_PINS[0]);
static const unsigned long BAUD_RATE = 115200UL;
static const uint8_t MAX_LINE = 32;  // characters of one command line, without the line end
static const unsigned long WDT_DEFAULT_MS = 2000UL;
static const unsigned long WDT_MIN_MS = 100UL;
static const unsigned long WDT_MAX_MS = 60000UL;

// Error codes of "ERR <code> <message>".
enum ErrorCode { ERR_UNKNOWN = 1, ERR_ARGUMENT = 2, ERR_TOO_LONG = 3, ERR_BAD_BYTE = 4 };

// What is lit: an LED index, NONE or ALL.
static const int8_t LIT_NONE = -1;
static const int8_t LIT_ALL = -2;

static char line[MAX_LINE + 1];
static uint8_t lineLength = 0;
static bool lineTooLong = false;
static bool lineBadByte = false;
static int8_t lit = LIT_NONE;
static unsigned long watchdogMs = WDT_DEFAULT_MS;
static unsigned long lastLineMs = 0;
static unsigned int watchdogTrips = 0;

static void setLeds(int8_t which) {
  // Switch off before switching on: two LEDs are never lit together by accident.
  for (uint8_t i = 0; i < LED_COUNT; i++) {
    digitalWrite(LED_PINS[i], LOW);
  }
  for (uint8_t i = 0; i < LED_COUNT; i++) {
    if (which == LIT_ALL || which == (int8_t)i) {
      digitalWrite(LED_PINS[i], HIGH);
    }
  }
  lit = which;
}

static void printIdentity() {
  Serial.print(FIRMWARE_NAME);
  Serial.print(' ');
  Serial.print(FIRMWARE_VERSION);
  Serial.print(F(" leds="));
  Serial.print(LED_COUNT);
  Serial.print(F(" wdt="));
  Serial.print(watchdogMs);
}

static void replyError(uint8_t code, const __FlashStringHelper *message) {
  Serial.print(F("ERR "));
  Serial.print(code);
  Serial.print(' ');
  Serial.println(message);
}

// Parse a decimal number that fills the whole of text; false for empty text, signs or other characters.
static bool parseNumber(const char *text, unsigned long *value) {
  if (*text == '\0' || strlen(text) > 5) {
    return false;
  }
  unsigned long result = 0;
  for (const char *c = text; *c != '\0'; c++) {
    if (*c < '0' || *c > '9') {
      return false;
    }
    result = result * 10UL + (unsigned long)(*c - '0');
  }
  *value = result;
  return true;
}

static void handleLine() {
  unsigned long number = 0;
  if (strcmp(line, "PING") == 0) {
    Serial.println(F("OK PING"));
  } else if (strcmp(line, "ID?") == 0) {
    Serial.print(F("OK ID "));
    printIdentity();
    Serial.println();
  } else if (strncmp(line, "ON ", 3) == 0) {
    if (!parseNumber(line + 3, &number) || number >= LED_COUNT) {
      replyError(ERR_ARGUMENT, F("led index out of range"));
      return;
    }
    setLeds((int8_t)number);
    Serial.print(F("OK ON "));
    Serial.println(number);
  } else if (strcmp(line, "ALL") == 0) {
    setLeds(LIT_ALL);
    Serial.println(F("OK ALL"));
  } else if (strcmp(line, "OFF") == 0) {
    setLeds(LIT_NONE);
    Serial.println(F("OK OFF"));
  } else if (strcmp(line, "STATE?") == 0) {
    Serial.print(F("OK STATE on="));
    if (lit == LIT_NONE) {
      Serial.print('-');
    } else if (lit == LIT_ALL) {
      Serial.print(F("all"));
    } else {
      Serial.print(lit);
    }
    Serial.print(F(" wdt="));
    Serial.print(watchdogMs);
    Serial.print(F(" trips="));
    Serial.println(watchdogTrips);
  } else if (strncmp(line, "WDT ", 4) == 0) {
    if (!parseNumber(line + 4, &number) || number < WDT_MIN_MS || number > WDT_MAX_MS) {
      replyError(ERR_ARGUMENT, F("watchdog ms out of range 100..60000"));
      return;
    }
    watchdogMs = number;
    Serial.print(F("OK WDT "));
    Serial.println(number);
  } else {
    replyError(ERR_UNKNOWN, F("unknown command"));
  }
}

static void endOfLine() {
  lastLineMs = millis();  // any complete line, even a bad one, shows the host is alive
  if (lineTooLong) {
    replyError(ERR_TOO_LONG, F("line too long"));
  } else if (lineBadByte) {
    replyError(ERR_BAD_BYTE, F("non-ASCII byte"));
  } else if (lineLength > 0) {
    line[lineLength] = '\0';
    handleLine();
  }
  lineLength = 0;
  lineTooLong = false;
  lineBadByte = false;
}

// Take the bytes that have arrived, never waiting for more.
static void pollSerial() {
  while (Serial.available() > 0) {
    int c = Serial.read();
    if (c == '\n') {
      endOfLine();
    } else if (c == '\r') {
      continue;
    } else if (c < 0x20 || c > 0x7E) {
      lineBadByte = true;
    } else if (lineLength < MAX_LINE) {
      line[lineLength++] = (char)c;
    } else {
      lineTooLong = true;
    }
  }
}

static void pollWatchdog() {
  // Unsigned subtraction stays right across the millis() wrap after 49.7 days.
  if (lit != LIT_NONE && (unsigned long)(millis() - lastLineMs) >= watchdogMs) {
    setLeds(LIT_NONE);
    watchdogTrips++;
  }
}

void setup() {
  for (uint8_t i = 0; i < LED_COUNT; i++) {
    pinMode(LED_PINS[i], OUTPUT);
    digitalWrite(LED_PINS[i], LOW);
  }
  Serial.begin(BAUD_RATE);
  lastLineMs = millis();
  Serial.print(F("READY "));
  printIdentity();
  Serial.println();
}

void loop() {
  pollSerial();
  pollWatchdog();
}
