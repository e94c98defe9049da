// A host stand-in for the few Arduino APIs the psmini-leds sketch uses, so that the sketch itself can be
// compiled with the host's g++ and driven byte by byte by tests/rig/test_firmware.py.
#pragma once

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <string>

#define HIGH 1
#define LOW 0
#define OUTPUT 1

class __FlashStringHelper;
#define F(literal) (reinterpret_cast<const __FlashStringHelper *>(literal))

unsigned long millis();
void pinMode(uint8_t pin, uint8_t mode);
void digitalWrite(uint8_t pin, uint8_t value);

// Print's overloads as on the AVR core: chars as characters, other integers as decimal numbers.
class HostSerial {
 public:
  std::string input;
  std::string output;

  void begin(unsigned long) {}
  int available() { return static_cast<int>(input.size()); }
  int read() {
    if (input.empty()) return -1;
    int c = static_cast<unsigned char>(input[0]);
    input.erase(0, 1);
    return c;
  }
  void print(const char *text) { output += text; }
  void print(const __FlashStringHelper *text) { output += reinterpret_cast<const char *>(text); }
  void print(char c) { output += c; }
  void print(unsigned char value) { print(static_cast<unsigned long>(value)); }
  void print(int value) { print(static_cast<long>(value)); }
  void print(unsigned int value) { print(static_cast<unsigned long>(value)); }
  void print(long value) { output += std::to_string(value); }
  void print(unsigned long value) { output += std::to_string(value); }
  void println() { output += "\r\n"; }
  template <typename T>
  void println(T value) {
    print(value);
    println();
  }
};

extern HostSerial Serial;
