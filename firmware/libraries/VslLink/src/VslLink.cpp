// VslLink: see VslLink.h and firmware/PROTOCOL.md.
#include "VslLink.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

namespace vsl {

static const char *const ERROR_NAMES[] = {"", "CHECKSUM", "MALFORMED", "UNKNOWN", "ARGS", "RANGE"};

static char rxBuf[MAX_BODY + 5];
static uint8_t rxLen = 0;
static bool rxOverflow = false;

uint8_t checksum(const char *body) {
  uint8_t sum = 0;
  while (*body) sum ^= (uint8_t)*body++;
  return sum;
}

void sendLine(const char *body) {
  char tail[5];
  snprintf(tail, sizeof(tail), "*%02X\n", checksum(body));
  Serial.write(body);
  Serial.write(tail);
}

void sendError(const char *tag, uint8_t code) {
  char body[32];
  snprintf(body, sizeof(body), "ERR %s %u %s", tag, code, ERROR_NAMES[code]);
  sendLine(body);
}

void sendOk(const char *tag, const char *verb) {
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

uint8_t parseArg(const char *text, int32_t lo, int32_t hi, int32_t *out) {
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

// Split "<tag> <VERB> [args]" in place and hand it over; a bad tag is a transport error (tag "-").
static void dispatch(char *body, CommandHandler handler) {
  char *save = NULL;
  Command cmd = {NULL, NULL, {NULL, NULL, NULL}, 0};
  char *tag = strtok_r(body, " ", &save);
  char *verb = strtok_r(NULL, " ", &save);
  if (tag == NULL || verb == NULL || strlen(tag) > 5) return sendError("-", E_MALFORMED);
  for (const char *p = tag; *p; p++) {
    if (*p < '0' || *p > '9') return sendError("-", E_MALFORMED);
  }
  if (atol(tag) > 65535L) return sendError("-", E_MALFORMED);
  cmd.tag = tag;
  cmd.verb = verb;
  char *a;
  while ((a = strtok_r(NULL, " ", &save)) != NULL) {
    if (cmd.nargs == MAX_ARGS) return sendError(tag, E_ARGS);
    cmd.args[cmd.nargs++] = a;
  }
  handler(cmd);
}

// A complete line (without '\n') is in rxBuf: check framing and checksum, then dispatch.
static void handleLine(CommandHandler handler) {
  if (rxLen > 0 && rxBuf[rxLen - 1] == '\r') rxLen--;
  rxBuf[rxLen] = '\0';
  char *star = strrchr(rxBuf, '*');
  if (star == NULL || (rxBuf + rxLen) - star != 3 || star - rxBuf > MAX_BODY) return sendError("-", E_MALFORMED);
  int hi = hexDigit(star[1]), lo = hexDigit(star[2]);
  *star = '\0';
  for (const char *p = rxBuf; *p; p++) {
    if (*p < 0x20 || *p > 0x7E) return sendError("-", E_MALFORMED);
  }
  if (hi < 0 || lo < 0) return sendError("-", E_MALFORMED);
  if (checksum(rxBuf) != (uint8_t)((hi << 4) | lo)) return sendError("-", E_CHECKSUM);
  dispatch(rxBuf, handler);
}

void pollSerial(CommandHandler handler) {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\n') {
      if (rxOverflow) sendError("-", E_MALFORMED);
      else handleLine(handler);
      rxLen = 0;
      rxOverflow = false;
    } else if (rxLen >= sizeof(rxBuf) - 1) {
      rxOverflow = true;  // discard up to the next '\n'
    } else {
      rxBuf[rxLen++] = c;
    }
  }
}

void StreamClock::setRate(int32_t rateHz, uint32_t nowUs) {
  periodUs = rateHz > 0 ? 1000000UL / (uint32_t)rateHz : 0;
  nextUs = nowUs;  // first sample on the next loop pass
}

void StreamClock::answerStream(const Command &cmd, int32_t maxHz) {
  int32_t rateHz = 0;
  uint8_t err = 0;
  if (cmd.nargs != 1) return sendError(cmd.tag, E_ARGS);
  if ((err = parseArg(cmd.args[0], 0, maxHz, &rateHz))) return sendError(cmd.tag, err);
  setRate(rateHz, micros());
  sendOk(cmd.tag, "STREAM");
}

bool StreamClock::due(uint32_t nowUs) {
  if (periodUs == 0 || (int32_t)(nowUs - nextUs) < 0) return false;  // off, or not due (wrap-safe)
  nextUs += periodUs;
  if ((int32_t)(nowUs - nextUs) >= 0) nextUs = nowUs + periodUs;  // a period behind: skip, never burst
  return true;
}

}  // namespace vsl
