// Host harness for a VSL sketch: compiles the sketch itself (SKETCH, e.g. "pressure_board.ino") and
// VslLink against the stand-ins in this folder, then answers on stdout, one line per stdin line:
//   stdin : <hex bytes>      bytes for the board's UART (may hold several lines, a partial one, nothing)
//   stdout: <hex bytes>      everything the board wrote while its serial parser took them
// The first stdout line is what setup() wrote (READY). Built and driven by tests/test_board_vectors.py:
//   g++ -std=c++17 -I firmware/test/host -I firmware/libraries/VslLink/src -I firmware/<board>
//       -DSKETCH='"<board>.ino"' firmware/test/host/harness.cpp firmware/libraries/VslLink/src/VslLink.cpp
#include <Arduino.h>

#include <iostream>

#include SKETCH

static std::string takeOutput() {
  static const char *digits = "0123456789abcdef";
  std::string hex;
  for (unsigned char c : Serial.tx) {
    hex += digits[c >> 4];
    hex += digits[c & 15];
  }
  Serial.tx.clear();
  return hex;
}

static int nibble(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

int main() {
  setup();
  std::cout << takeOutput() << std::endl;
  std::string line;
  while (std::getline(std::cin, line)) {
    std::string bytes;
    for (size_t i = 0; i + 1 < line.size(); i += 2) {
      int hi = nibble(line[i]), lo = nibble(line[i + 1]);
      if (hi < 0 || lo < 0) {
        std::cerr << "harness: not hex: " << line << std::endl;
        return 2;
      }
      bytes += (char)((hi << 4) | lo);
    }
    Serial.rx = bytes;
    Serial.rxPos = 0;
    vsl::pollSerial(handleCommand);  // the sketch's own handler: one pass of loop()'s serial part
    std::cout << takeOutput() << std::endl;
  }
  return 0;
}
