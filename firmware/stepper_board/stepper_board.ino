// VSL stepper board (Arduino Nano): the J1 stepper through an A4988.
// Protocol: ../PROTOCOL.md (v1.0). 250000 baud, lines "<BODY>*<XX>\n", XOR checksum, tagged commands.
//
// Wiring (ASSUMPTIONS, check against the rig):
//   D3 -> A4988 STEP, D4 -> DIR, D5 -> /ENABLE (LOW = enabled)
//   D6, D7, D8 -> MS1, MS2, MS3 (all HIGH = 1/16 microstepping; positions are in microsteps)
// AccelStepper::run() is called on every loop pass; serial parsing and streaming never block.
// No dynamic allocation: fixed buffers only.

#include <AccelStepper.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char BOARD[] = "STEPPER";
static const char FIRMWARE[] = "1.0.0";
static const char SERIAL_LABEL[] = "VSLS-0001";  // the unit's label, set per board before flashing

static const uint32_t BAUD = 250000UL;
static const uint8_t PIN_STEP = 3, PIN_DIR = 4, PIN_ENABLE = 5;
static const uint8_t PIN_MS[3] = {6, 7, 8};
static const int32_t MAX_ABS_STEPS = 2000000L;
static const int32_t MAX_SPEED = 4000;  // microsteps/s: AccelStepper's practical limit on 16 MHz
static const int32_t MAX_ACCEL = 100000L;
static const int32_t MAX_STREAM_HZ = 200;
static const uint8_t MAX_BODY = 63;

enum ErrorCode { E_CHECKSUM = 1, E_MALFORMED = 2, E_UNKNOWN = 3, E_ARGS = 4, E_RANGE = 5 };
static const char *const ERROR_NAMES[] = {"", "CHECKSUM", "MALFORMED", "UNKNOWN", "ARGS", "RANGE"};

AccelStepper stepper(AccelStepper::DRIVER, PIN_STEP, PIN_DIR);

// receive state
static char rxBuf[MAX_BODY + 5];  // body + "*XX" + optional '\r' + NUL
static uint8_t rxLen = 0;
static bool rxOverflow = false;

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
  char reply[MAX_BODY + 1];

  if (strcmp(verb, "ID?") == 0) {
    if (nargs != 0) return sendError(tag, E_ARGS);
    snprintf(reply, sizeof(reply), "ID %s %s %s %s", tag, BOARD, FIRMWARE, SERIAL_LABEL);
    sendLine(reply);
  } else if (strcmp(verb, "MOVE") == 0) {
    if (nargs != 1) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], -MAX_ABS_STEPS, MAX_ABS_STEPS, &x))) return sendError(tag, err);
    stepper.moveTo(x);
    sendOk(tag, "MOVE");
  } else if (strcmp(verb, "SPEED") == 0) {
    if (nargs != 2) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], 1, MAX_SPEED, &x)) || (err = parseArg(args[1], 1, MAX_ACCEL, &y))) {
      return sendError(tag, err);
    }
    stepper.setMaxSpeed((float)x);
    stepper.setAcceleration((float)y);
    sendOk(tag, "SPEED");
  } else if (strcmp(verb, "POS?") == 0) {
    if (nargs != 0) return sendError(tag, E_ARGS);
    snprintf(reply, sizeof(reply), "POS %s %lu %ld %u", tag, (unsigned long)micros(),
             (long)stepper.currentPosition(), (unsigned)(stepper.distanceToGo() != 0));
    sendLine(reply);
  } else if (strcmp(verb, "STREAM") == 0) {
    if (nargs != 1) return sendError(tag, E_ARGS);
    if ((err = parseArg(args[0], 0, MAX_STREAM_HZ, &x))) return sendError(tag, err);
    streamPeriodUs = x ? 1000000UL / (uint32_t)x : 0;
    nextSampleUs = micros();  // first sample on the next loop pass
    sendOk(tag, "STREAM");
  } else if (strcmp(verb, "STOP") == 0) {
    if (nargs != 0) return sendError(tag, E_ARGS);
    stepper.stop();  // decelerate to a stop at the current acceleration
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

// ------------------------------------------------------------------------------------ streaming
static void pollStream() {
  if (streamPeriodUs == 0) return;
  uint32_t now = micros();
  if ((int32_t)(now - nextSampleUs) < 0) return;  // not due (wrap-safe)
  nextSampleUs += streamPeriodUs;
  if ((int32_t)(now - nextSampleUs) >= 0) nextSampleUs = now + streamPeriodUs;  // a period behind: skip
  char body[MAX_BODY + 1];
  snprintf(body, sizeof(body), "S %lu %lu %ld %u", (unsigned long)sampleSeq, (unsigned long)now,
           (long)stepper.currentPosition(), (unsigned)(stepper.distanceToGo() != 0));
  sendLine(body);
  sampleSeq++;
}

// ----------------------------------------------------------------------------------------- main
void setup() {
  for (uint8_t i = 0; i < 3; i++) {
    pinMode(PIN_MS[i], OUTPUT);
    digitalWrite(PIN_MS[i], HIGH);  // 1/16 microstepping
  }
  pinMode(PIN_ENABLE, OUTPUT);
  digitalWrite(PIN_ENABLE, LOW);  // driver enabled (holds the position)
  stepper.setMaxSpeed(1000.0);
  stepper.setAcceleration(5000.0);
  stepper.setCurrentPosition(0);  // the host homes J1; position 0 is where the board was reset

  Serial.begin(BAUD);
  char body[MAX_BODY + 1];
  snprintf(body, sizeof(body), "READY %s %s", BOARD, FIRMWARE);
  sendLine(body);
}

void loop() {
  stepper.run();
  pollSerial();
  stepper.run();
  pollStream();
}
