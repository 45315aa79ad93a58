// VSL pressure board (Arduino Uno): two Camozzi K8P regulators, two solenoid valves, two transducers.
// Protocol: ../PROTOCOL.md (v1.0). 250000 baud, lines "<BODY>*<XX>\n", XOR checksum, tagged commands.
//
// Wiring (ASSUMPTIONS, check against the rig):
//   D9  (OC1A) -> L298 ENA -> OUT1/OUT2 -> RC -> regulator 0 set-point input (0-10 V); IN1 high, IN2 low
//   D10 (OC1B) -> L298 ENB -> OUT3/OUT4 -> RC -> regulator 1 set-point input (0-10 V); IN3 high, IN4 low
//   D7, D8     -> valve drivers (HIGH = energised = open)
//   A4/A5      -> ADS1115 SDA/SCL (address 0x48), AIN0/AIN1 <- transducers 0/1 (0.5-4.5 V)
// No dynamic allocation: fixed buffers only. Needs Adafruit_ADS1X15 >= 2.0 (non-blocking API).

#include <Adafruit_ADS1X15.h>
#include <Wire.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char BOARD[] = "PRESSURE";
static const char FIRMWARE[] = "1.0.0";
static const char SERIAL_LABEL[] = "VSLP-0001";  // the unit's label, set per board before flashing

static const uint32_t BAUD = 250000UL;
static const uint8_t PIN_VALVE[2] = {7, 8};
static const uint16_t PWM_TOP = 1023;                    // Timer1 fast PWM, 16 MHz / 1024 = 15.6 kHz
static const uint32_t REGULATOR_FULL_SCALE_PA = 1000000UL;  // ASSUMPTION: 10 V <-> 10 bar
static const int32_t MAX_SET_PA = 400000L;
static const int32_t MAX_STREAM_HZ = 200;
static const uint8_t MAX_BODY = 63;

enum ErrorCode { E_CHECKSUM = 1, E_MALFORMED = 2, E_UNKNOWN = 3, E_ARGS = 4, E_RANGE = 5 };
static const char *const ERROR_NAMES[] = {"", "CHECKSUM", "MALFORMED", "UNKNOWN", "ARGS", "RANGE"};

Adafruit_ADS1115 ads;

// receive state
static char rxBuf[MAX_BODY + 5];  // body + "*XX" + optional '\r' + NUL
static uint8_t rxLen = 0;
static bool rxOverflow = false;

// outputs and samples
static uint8_t valveBits = 0;
static int16_t counts[2] = {INT16_MIN, INT16_MIN};  // -32768: no conversion (ADS1115 missing)
static uint8_t adcChannel = 0;
static bool adcOk = false;

// streaming
static uint32_t streamPeriodUs = 0;  // 0 = off
static uint32_t nextSampleUs = 0;
static uint32_t sampleSeq = 0;

// ----------------------------------------------------------------------------------------- framing
static uint8_t xorChecksum(const char *body) {
  uint8_t sum = 0;
  while (*body) sum ^= (uint8_t)*body++;
  return sum;
}

// Send "<body>*XX\n". The body must not contain '*'.
static void sendLine(const char *body) {
  char tail[5];
  snprintf(tail, sizeof(tail), "*%02X\n", xorChecksum(body));
  Serial.write(body);
  Serial.write(tail);
}

static void sendError(const char *tag, uint8_t code) {
  char body[32];
  snprintf(body, sizeof(body), "ERR %s %u %s", tag, code, ERROR_NAMES[code]);
  sendLine(body);
}

static void sendOk(const char *tag, const char *verb) {
  char body[32];
  snprintf(body, sizeof(body), "OK %s %s", tag, verb);
  sendLine(body);
}

static int hexDigit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// Parse a decimal integer argument into *out within [lo, hi]; returns 0, E_ARGS or E_RANGE.
static uint8_t parseArg(const char *text, int32_t lo, int32_t hi, int32_t *out) {
  if (text == NULL || *text == '\0') return E_ARGS;
  const char *digits = (*text == '-' || *text == '+') ? text + 1 : text;
  size_t n = strlen(digits);
  if (n == 0 || n > 10) return E_ARGS;
  for (size_t i = 0; i < n; i++) {
    if (digits[i] < '0' || digits[i] > '9') return E_ARGS;
  }
  long value = strtol(text, NULL, 10);
  if (value < lo || value > hi) return E_RANGE;
  *out = (int32_t)value;
  return 0;
}

// ---------------------------------------------------------------------------------------- outputs
static void setPressure(uint8_t channel, int32_t pa) {
  uint16_t duty = (uint16_t)(((uint32_t)pa * PWM_TOP + REGULATOR_FULL_SCALE_PA / 2) / REGULATOR_FULL_SCALE_PA);
  if (channel == 0) OCR1A = duty;
  else OCR1B = duty;
}

static void setValve(uint8_t channel, bool open) {
  digitalWrite(PIN_VALVE[channel], open ? HIGH : LOW);
  if (open) valveBits |= (uint8_t)(1u << channel);
  else valveBits &= (uint8_t)~(1u << channel);
}

static void safeState() {
  setPressure(0, 0);
  setPressure(1, 0);
  setValve(0, false);
  setValve(1, false);
  streamPeriodUs = 0;
}

// --------------------------------------------------------------------------------------- commands
static void handleCommand(char *body) {
  char *save = NULL;
  char *tag = strtok_r(body, " ", &save);
  char *verb = strtok_r(NULL, " ", &save);
  if (tag == NULL || verb == NULL || strlen(tag) > 5) {
    sendError("-", E_MALFORMED);
    return;
  }
  for (const char *p = tag; *p; p++) {
    if (*p < '0' || *p > '9') {
      sendError("-", E_MALFORMED);
      return;
    }
  }
  if (atol(tag) > 65535L) {
    sendError("-", E_MALFORMED);
    return;
  }
  char *args[3] = {NULL, NULL, NULL};
  uint8_t nargs = 0;
  char *a;
  while ((a = strtok_r(NULL, " ", &save)) != NULL) {
    if (nargs == 3) {
      sendError(tag, E_ARGS);
      return;
    }
    args[nargs++] = a;
  }
  int32_t x = 0, y = 0;
  uint8_t err = 0;

  if (strcmp(verb, "ID?") == 0) {
    if (nargs != 0) return sendError(tag, E_ARGS);
    char reply[MAX_BODY + 1];
    snprintf(reply, sizeof(reply), "ID %s %s %s %s", tag, BOARD, FIRMWARE, SERIAL_LABEL);
    sendLine(reply);
  } else if (strcmp(verb, "SET") == 0) {
    if (nargs != 2) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], 0, 1, &x)) || (err = parseArg(args[1], 0, MAX_SET_PA, &y))) {
      return sendError(tag, err);
    }
    setPressure((uint8_t)x, y);
    sendOk(tag, "SET");
  } else if (strcmp(verb, "VALVE") == 0) {
    if (nargs != 2) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], 0, 1, &x)) || (err = parseArg(args[1], 0, 1, &y))) {
      return sendError(tag, err);
    }
    setValve((uint8_t)x, y != 0);
    sendOk(tag, "VALVE");
  } else if (strcmp(verb, "STREAM") == 0) {
    if (nargs != 1) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], 0, MAX_STREAM_HZ, &x))) return sendError(tag, err);
    streamPeriodUs = x ? 1000000UL / (uint32_t)x : 0;
    nextSampleUs = micros();  // first sample on the next loop pass
    sendOk(tag, "STREAM");
  } else if (strcmp(verb, "STOP") == 0) {
    if (nargs != 0) return sendError(tag, E_ARGS);
    safeState();
    sendOk(tag, "STOP");
  } else {
    sendError(tag, E_UNKNOWN);
  }
}

// A complete line (without '\n') is in rxBuf: check framing and checksum, then dispatch.
static void handleLine() {
  if (rxLen > 0 && rxBuf[rxLen - 1] == '\r') rxLen--;
  rxBuf[rxLen] = '\0';
  char *star = strrchr(rxBuf, '*');
  if (star == NULL || (rxBuf + rxLen) - star != 3 || star - rxBuf > MAX_BODY) {
    sendError("-", E_MALFORMED);
    return;
  }
  int hi = hexDigit(star[1]), lo = hexDigit(star[2]);
  *star = '\0';
  for (const char *p = rxBuf; *p; p++) {
    if (*p < 0x20 || *p > 0x7E) {
      sendError("-", E_MALFORMED);
      return;
    }
  }
  if (hi < 0 || lo < 0) {
    sendError("-", E_MALFORMED);
    return;
  }
  if (xorChecksum(rxBuf) != (uint8_t)((hi << 4) | lo)) {
    sendError("-", E_CHECKSUM);
    return;
  }
  handleCommand(rxBuf);
}

// Non-blocking: consume what the UART has buffered, one line at a time.
static void pollSerial() {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\n') {
      if (rxOverflow) sendError("-", E_MALFORMED);
      else handleLine();
      rxLen = 0;
      rxOverflow = false;
    } else if (rxLen >= sizeof(rxBuf) - 1) {
      rxOverflow = true;  // discard up to the next '\n'
    } else {
      rxBuf[rxLen++] = c;
    }
  }
}

// ------------------------------------------------------------------------------------------ ADC
static uint16_t muxFor(uint8_t channel) {
  return channel == 0 ? ADS1X15_REG_CONFIG_MUX_SINGLE_0 : ADS1X15_REG_CONFIG_MUX_SINGLE_1;
}

// Alternate AIN0/AIN1 single-shot conversions without blocking (860 SPS: ~1.2 ms each).
static void pollAdc() {
  if (!adcOk || !ads.conversionComplete()) return;
  counts[adcChannel] = ads.getLastConversionResults();
  adcChannel ^= 1;
  ads.startADCReading(muxFor(adcChannel), /*continuous=*/false);
}

// ------------------------------------------------------------------------------------ streaming
static void pollStream() {
  if (streamPeriodUs == 0) return;
  uint32_t now = micros();
  if ((int32_t)(now - nextSampleUs) < 0) return;  // not due (wrap-safe)
  nextSampleUs += streamPeriodUs;
  if ((int32_t)(now - nextSampleUs) >= 0) nextSampleUs = now + streamPeriodUs;  // a period behind: skip
  char body[MAX_BODY + 1];
  snprintf(body, sizeof(body), "P %lu %lu %d %d %u", (unsigned long)sampleSeq, (unsigned long)now,
           (int)counts[0], (int)counts[1], (unsigned)valveBits);
  sendLine(body);
  sampleSeq++;
}

// ----------------------------------------------------------------------------------------- main
void setup() {
  pinMode(9, OUTPUT);
  pinMode(10, OUTPUT);
  // Timer1: fast PWM mode 14 (TOP = ICR1), non-inverting on OC1A/OC1B, no prescaler.
  TCCR1A = _BV(COM1A1) | _BV(COM1B1) | _BV(WGM11);
  TCCR1B = _BV(WGM13) | _BV(WGM12) | _BV(CS10);
  ICR1 = PWM_TOP;
  for (uint8_t ch = 0; ch < 2; ch++) pinMode(PIN_VALVE[ch], OUTPUT);
  safeState();

  Serial.begin(BAUD);
  ads.setGain(GAIN_ONE);  // +-4.096 V, 125 uV/LSB
  ads.setDataRate(RATE_ADS1115_860SPS);
  adcOk = ads.begin(0x48);  // without the ADC the board still answers; P lines then carry -32768
  Wire.setClock(400000);    // after begin(): Wire.begin() resets the bus to 100 kHz
  if (adcOk) ads.startADCReading(muxFor(adcChannel), /*continuous=*/false);
  char body[MAX_BODY + 1];
  snprintf(body, sizeof(body), "READY %s %s", BOARD, FIRMWARE);
  sendLine(body);
}

void loop() {
  pollSerial();
  pollAdc();
  pollStream();
}
