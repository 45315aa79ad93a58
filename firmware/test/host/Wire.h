// Host stand-in for <Wire.h> (firmware/test/host/Arduino.h explains why).
#pragma once

#include <Arduino.h>

class TwoWire {
 public:
  void begin() {}
  void setClock(uint32_t) {}
};
inline TwoWire Wire;
