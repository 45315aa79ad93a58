// Host stand-in for Adafruit_ADS1X15 (>= 2.0): an ADS1115 that is not there (begin() fails, as on a
// board whose ADC does not answer), so P lines would carry -32768. Only the calls the sketch makes.
#pragma once

#include <Arduino.h>

#define ADS1X15_REG_CONFIG_MUX_SINGLE_0 (0x4000)
#define ADS1X15_REG_CONFIG_MUX_SINGLE_1 (0x5000)
enum adsGain_t { GAIN_TWOTHIRDS = 0x0000, GAIN_ONE = 0x0200 };
enum { RATE_ADS1115_860SPS = 0x00E0 };

class Adafruit_ADS1115 {
 public:
  bool begin(uint8_t = 0x48) { return false; }
  void setGain(adsGain_t) {}
  void setDataRate(uint16_t) {}
  void startADCReading(uint16_t, bool) {}
  bool conversionComplete() { return false; }
  int16_t getLastConversionResults() { return 0; }
};
