// Runs the psmini-leds sketch on the host. Commands on stdin, one per line:
//   x HEX   the bytes HEX arrive on the serial line, then loop() runs
//   t MS    MS milliseconds pass, then loop() runs
//   s       print the LED pins
// After each command it prints "OUT <hex of the serial output so far, then cleared>" and, for s, "LEDS <D2..D9>".
#include <Arduino.h>

#include <cstdio>
#include <iostream>
#include <string>

static unsigned long nowMs = 0;
static uint8_t pinLevels[20];
static uint8_t pinModes[20];

unsigned long millis() { return nowMs; }
void pinMode(uint8_t pin, uint8_t mode) { pinModes[pin] = mode; }
void digitalWrite(uint8_t pin, uint8_t value) { pinLevels[pin] = value; }
HostSerial Serial;

#include "psmini_leds.ino"

static void flushOutput() {
  std::printf("OUT ");
  for (unsigned char c : Serial.output) std::printf("%02x", c);
  std::printf("\n");
  Serial.output.clear();
}

int main() {
  setup();
  flushOutput();
  std::string op;
  while (std::cin >> op) {
    if (op == "x") {
      std::string hex;
      std::cin >> hex;
      for (size_t i = 0; i + 1 < hex.size(); i += 2) {
        Serial.input += static_cast<char>(std::stoi(hex.substr(i, 2), nullptr, 16));
      }
      loop();
    } else if (op == "t") {
      unsigned long ms = 0;
      std::cin >> ms;
      nowMs += ms;
      loop();
    } else if (op == "s") {
      std::printf("LEDS ");
      for (uint8_t i = 0; i < LED_COUNT; i++) {
        std::printf("%d", pinModes[LED_PINS[i]] == OUTPUT && pinLevels[LED_PINS[i]] == HIGH ? 1 : 0);
      }
      std::printf("\n");
    }
    flushOutput();
  }
  return 0;
}
