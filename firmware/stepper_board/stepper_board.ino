// VSL stepper board (Arduino Nano): the J1 stepper through an A4988.
// Protocol: ../PROTOCOL.md (v1.0), implemented by the VslLink library (../libraries/VslLink); this sketch
// only implements the board's verbs and samples.
//
// Wiring (ASSUMPTIONS, check against the rig):
//   D3 -> A4988 STEP, D4 -> DIR, D5 -> /ENABLE (LOW = enabled)
//   D6, D7, D8 -> MS1, MS2, MS3 (all HIGH = 1/16 microstepping; positions are in microsteps)
// AccelStepper::run() is called on every loop pass; serial parsing and streaming never block.
// No dynamic allocation: fixed buffers only.

#include <AccelStepper.h>
#include <VslLink.h>
#include <stdio.h>
#include <string.h>

// Deliberate mirror of ../pressure_board/pressure_board.ino: each sketch is a whole firmware image and opens alike
// (identity, baud, the verbs it answers); what they share at run time is the VslLink library.
using vsl::E_ARGS;
using vsl::E_UNKNOWN;

static const char BOARD[] = "STEPPER";
static const char FIRMWARE[] = "1.0.0";
static const char SERIAL_LABEL[] = "VSLS-0001";  // the unit's label, set per board before flashing

static const uint32_t BAUD = 250000UL;
static const uint8_t PIN_STEP = 3, PIN_DIR = 4, PIN_ENABLE = 5;
static const uint8_t PIN_MS[3] = {6, 7, 8};
static const int32_t MAX_ABS_STEPS = 2000000L;
static const int32_t MAX_SPEED = 4000;  // microsteps/s: AccelStepper's practical limit on 16 MHz
static const int32_t MAX_ACCEL = 100000L;
static const int32_t MAX_STREAM_HZ = 250;

AccelStepper stepper(AccelStepper::DRIVER, PIN_STEP, PIN_DIR);
static vsl::StreamClock stream = {0, 0, 0};

// --------------------------------------------------------------------------------------- commands
static void handleCommand(const vsl::Command &cmd) {
  const char *tag = cmd.tag;
  int32_t x = 0, y = 0;
  uint8_t err = 0;
  char reply[vsl::MAX_BODY + 1];
  if (strcmp(cmd.verb, "ID?") == 0) {
    if (cmd.nargs != 0) return vsl::sendError(tag, E_ARGS);
    snprintf(reply, sizeof(reply), "ID %s %s %s %s", tag, BOARD, FIRMWARE, SERIAL_LABEL);
    vsl::sendLine(reply);
  } else if (strcmp(cmd.verb, "MOVE") == 0) {
    if (cmd.nargs != 1) return vsl::sendError(tag, E_ARGS);
    if ((err = vsl::parseArg(cmd.args[0], -MAX_ABS_STEPS, MAX_ABS_STEPS, &x))) return vsl::sendError(tag, err);
    stepper.moveTo(x);
    vsl::sendOk(tag, "MOVE");
  } else if (strcmp(cmd.verb, "SPEED") == 0) {
    if (cmd.nargs != 2) return vsl::sendError(tag, E_ARGS);
    if ((err = vsl::parseArg(cmd.args[0], 1, MAX_SPEED, &x)) || (err = vsl::parseArg(cmd.args[1], 1, MAX_ACCEL, &y))) {
      return vsl::sendError(tag, err);
    }
    stepper.setMaxSpeed((float)x);
    stepper.setAcceleration((float)y);
    vsl::sendOk(tag, "SPEED");
  } else if (strcmp(cmd.verb, "POS?") == 0) {
    if (cmd.nargs != 0) return vsl::sendError(tag, E_ARGS);
    snprintf(reply, sizeof(reply), "POS %s %lu %ld %u", tag, (unsigned long)micros(),
             (long)stepper.currentPosition(), (unsigned)(stepper.distanceToGo() != 0));
    vsl::sendLine(reply);
  } else if (strcmp(cmd.verb, "STREAM") == 0) {
    stream.answerStream(cmd, MAX_STREAM_HZ);
  } else if (strcmp(cmd.verb, "STOP") == 0) {
    if (cmd.nargs != 0) return vsl::sendError(tag, E_ARGS);
    stepper.stop();  // decelerate to a stop at the current acceleration
    vsl::sendOk(tag, "STOP");
  } else {
    vsl::sendError(tag, E_UNKNOWN);
  }
}

// ------------------------------------------------------------------------------------ streaming
static void pollStream() {
  uint32_t now = micros();
  if (!stream.due(now)) return;
  char body[vsl::MAX_BODY + 1];
  snprintf(body, sizeof(body), "S %lu %lu %ld %u", (unsigned long)stream.seq, (unsigned long)now,
           (long)stepper.currentPosition(), (unsigned)(stepper.distanceToGo() != 0));
  vsl::sendLine(body);
  stream.seq++;
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
  char body[vsl::MAX_BODY + 1];
  snprintf(body, sizeof(body), "READY %s %s", BOARD, FIRMWARE);
  vsl::sendLine(body);
}

void loop() {
  stepper.run();
  vsl::pollSerial(handleCommand);
  stepper.run();
  pollStream();
}
