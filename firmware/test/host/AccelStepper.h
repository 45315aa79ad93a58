// Host stand-in for AccelStepper: remembers the target and limits; the motor never steps (time is frozen
// in the harness), so distanceToGo() is the whole move and stop() ends it where the motor stands.
#pragma once

#include <Arduino.h>

class AccelStepper {
 public:
  enum MotorInterfaceType { DRIVER = 1 };
  long target = 0, position = 0;
  float maxSpeed = 1.0f, acceleration = 1.0f;
  AccelStepper(uint8_t, uint8_t, uint8_t) {}
  void moveTo(long absolute) { target = absolute; }
  void setMaxSpeed(float speed) { maxSpeed = speed; }
  void setAcceleration(float accel) { acceleration = accel; }
  void setCurrentPosition(long p) { position = target = p; }
  long currentPosition() { return position; }
  long distanceToGo() { return target - position; }
  void stop() { target = position; }
  bool run() { return target != position; }
};
