// Host stand-in for <Arduino.h>: only what the VSL sketches and VslLink touch, so that their command
// parsing compiles with g++ and runs against firmware/vectors.json (tests/test_board_vectors.py).
// Hardware is mocked (registers are plain variables, the UART is two byte strings); nothing of the
// protocol logic is re-implemented here.
#pragma once

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <string>

#define HIGH 0x1
#define LOW 0x0
#define INPUT 0x0
#define OUTPUT 0x1
#define _BV(bit) (1 << (bit))

// Timer1 registers and bits (ATmega328P) as plain variables.
inline uint8_t TCCR1A = 0, TCCR1B = 0;
inline uint16_t ICR1 = 0, OCR1A = 0, OCR1B = 0;
enum { CS10 = 0, WGM11 = 1, WGM12 = 3, WGM13 = 4, COM1B1 = 5, COM1A1 = 7 };

inline uint8_t mockPinMode[32];
inline uint8_t mockPinLevel[32];
inline void pinMode(uint8_t pin, uint8_t mode) { mockPinMode[pin & 31] = mode; }
inline void digitalWrite(uint8_t pin, uint8_t level) { mockPinLevel[pin & 31] = level; }

// micros() is frozen (the vectors' POS? replies carry it; the test passes firmware/vectors.json's value).
#ifndef VSL_MOCK_MICROS
#define VSL_MOCK_MICROS 52004112UL
#endif
inline uint32_t mockMicros = VSL_MOCK_MICROS;
inline unsigned long micros() { return mockMicros; }
inline unsigned long millis() { return mockMicros / 1000UL; }

// The UART: bytes the harness feeds in, bytes the sketch wrote out.
class MockSerial {
 public:
  std::string rx, tx;
  size_t rxPos = 0;
  void begin(unsigned long) {}
  int available() { return (int)(rx.size() - rxPos); }
  int read() { return rxPos < rx.size() ? (uint8_t)rx[rxPos++] : -1; }
  size_t write(const char *s) {
    tx += s;
    return strlen(s);
  }
  size_t write(uint8_t b) {
    tx += (char)b;
    return 1;
  }
};
inline MockSerial Serial;
