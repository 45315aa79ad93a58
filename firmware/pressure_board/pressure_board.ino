// VSL pressure board (Arduino Uno): two Camozzi K8P regulators, two solenoid valves, two transducers.
// Protocol: ../PROTOCOL.md (v1.0), implemented by the VslLink library (../libraries/VslLink); this sketch
// only implements the board's verbs and samples.
//
// Wiring (ASSUMPTIONS, check against the rig):
//   D9  (OC1A) -> L298 ENA -> OUT1/OUT2 -> RC -> regulator 0 set-point input (0-10 V); IN1 high, IN2 low
//   D10 (OC1B) -> L298 ENB -> OUT3/OUT4 -> RC -> regulator 1 set-point input (0-10 V); IN3 high, IN4 low
//   D7, D8     -> valve drivers (HIGH = energised = open)
//   A4/A5      -> ADS1115 SDA/SCL (address 0x48), AIN0/AIN1 <- transducers 0/1 (0.5-4.5 V)
// No dynamic allocation: fixed buffers only. Needs Adafruit_ADS1X15 >= 2.0 (non-blocking API).

#include <Adafruit_ADS1X15.h>
#include <VslLink.h>
#include <Wire.h>
#include <stdio.h>
#include <string.h>

// Deliberate mirror of ../stepper_board/stepper_board.ino: each sketch is a whole firmware image and opens alike
// (identity, baud, the verbs it answers); what they share at run time is the VslLink library.
using vsl::E_ARGS;
using vsl::E_UNKNOWN;

static const char BOARD[] = "PRESSURE";
static const char FIRMWARE[] = "1.0.0";
static const char SERIAL_LABEL[] = "VSLP-0001";  // the unit's label, set per board before flashing

static const uint32_t BAUD = 250000UL;
static const uint8_t PIN_VALVE[2] = {7, 8};
static const uint16_t PWM_TOP = 1023;                       // Timer1 fast PWM, 16 MHz / 1024 = 15.6 kHz
static const uint32_t REGULATOR_FULL_SCALE_PA = 1000000UL;  // ASSUMPTION: 10 V <-> 10 bar
static const int32_t MAX_SET_PA = 300000L;  // the regulators' 0-3 bar span (robot: regulator_max_pa)
static const int32_t MAX_STREAM_HZ = 250;

Adafruit_ADS1115 ads;

// outputs and samples
static uint8_t valveBits = 0;
static int16_t counts[2] = {INT16_MIN, INT16_MIN};  // -32768: no conversion (ADS1115 missing)
static uint8_t adcChannel = 0;
static bool adcOk = false;
static vsl::StreamClock stream = {0, 0, 0};

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
  stream.setRate(0, micros());
}

// --------------------------------------------------------------------------------------- commands
static void handleCommand(const vsl::Command &cmd) {
  const char *tag = cmd.tag;
  int32_t x = 0, y = 0;
  uint8_t err = 0;
  if (strcmp(cmd.verb, "ID?") == 0) {
    if (cmd.nargs != 0) return vsl::sendError(tag, E_ARGS);
    char reply[vsl::MAX_BODY + 1];
    snprintf(reply, sizeof(reply), "ID %s %s %s %s", tag, BOARD, FIRMWARE, SERIAL_LABEL);
    vsl::sendLine(reply);
  } else if (strcmp(cmd.verb, "SET") == 0) {
    if (cmd.nargs != 2) return vsl::sendError(tag, E_ARGS);
    if ((err = vsl::parseArg(cmd.args[0], 0, 1, &x)) || (err = vsl::parseArg(cmd.args[1], 0, MAX_SET_PA, &y))) {
      return vsl::sendError(tag, err);
    }
    setPressure((uint8_t)x, y);
    vsl::sendOk(tag, "SET");
  } else if (strcmp(cmd.verb, "VALVE") == 0) {
    if (cmd.nargs != 2) return vsl::sendError(tag, E_ARGS);
    if ((err = vsl::parseArg(cmd.args[0], 0, 1, &x)) || (err = vsl::parseArg(cmd.args[1], 0, 1, &y))) {
      return vsl::sendError(tag, err);
    }
    setValve((uint8_t)x, y != 0);
    vsl::sendOk(tag, "VALVE");
  } else if (strcmp(cmd.verb, "STREAM") == 0) {
    stream.answerStream(cmd, MAX_STREAM_HZ);
  } else if (strcmp(cmd.verb, "STOP") == 0) {
    if (cmd.nargs != 0) return vsl::sendError(tag, E_ARGS);
    safeState();
    vsl::sendOk(tag, "STOP");
  } else {
    vsl::sendError(tag, E_UNKNOWN);
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
  uint32_t now = micros();
  if (!stream.due(now)) return;
  char body[vsl::MAX_BODY + 1];
  snprintf(body, sizeof(body), "P %lu %lu %d %d %u", (unsigned long)stream.seq, (unsigned long)now,
           (int)counts[0], (int)counts[1], (unsigned)valveBits);
  vsl::sendLine(body);
  stream.seq++;
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
  char body[vsl::MAX_BODY + 1];
  snprintf(body, sizeof(body), "READY %s %s", BOARD, FIRMWARE);
  vsl::sendLine(body);
}

void loop() {
  vsl::pollSerial(handleCommand);
  pollAdc();
  pollStream();
}
