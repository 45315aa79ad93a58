// VslLink: the line protocol shared by the VSL boards (firmware/PROTOCOL.md, v1.0).
// Lines are "<BODY>*<XX>\n" with XX the XOR of the body bytes; commands are "<tag> <VERB> [args]".
// This library owns framing, checksums, tokenising, error replies and the streaming clock with its STREAM
// verb; each sketch only implements its own verbs. No dynamic allocation.
#pragma once

#include <Arduino.h>

namespace vsl {

const uint8_t MAX_BODY = 63;  // bytes of BODY; the receive buffer holds BODY + "*XX" + '\r' + NUL
const uint8_t MAX_ARGS = 3;

enum ErrorCode : uint8_t { E_CHECKSUM = 1, E_MALFORMED = 2, E_UNKNOWN = 3, E_ARGS = 4, E_RANGE = 5 };

// One received command, tokenised in place (pointers into the receive buffer, valid during the call).
struct Command {
  const char *tag;
  const char *verb;
  const char *args[MAX_ARGS];
  uint8_t nargs;
};
typedef void (*CommandHandler)(const Command &cmd);

uint8_t checksum(const char *body);
void sendLine(const char *body);  // body must not contain '*'
void sendOk(const char *tag, const char *verb);
void sendError(const char *tag, uint8_t code);

// Decimal integer argument within [lo, hi] into *out; returns 0, E_ARGS or E_RANGE.
uint8_t parseArg(const char *text, int32_t lo, int32_t hi, int32_t *out);

// Consume what the UART holds (never blocks). Each valid command goes to handler; malformed lines, bad
// checksums, bad tags and too many arguments are answered here.
void pollSerial(CommandHandler handler);

// Samples streamed on the board's own micros(): 0 Hz = off. due() is wrap-safe and skips a slot rather
// than sending late; seq counts the samples sent.
struct StreamClock {
  uint32_t periodUs;
  uint32_t nextUs;
  uint32_t seq;
  void setRate(int32_t rateHz, uint32_t nowUs);
  bool due(uint32_t nowUs);
  // The STREAM verb, alike on every board: "STREAM <rate_hz 0..maxHz>" sets the rate, answered OK or ERR.
  void answerStream(const Command &cmd, int32_t maxHz);
};

}  // namespace vsl
