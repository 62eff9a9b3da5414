// A small Arduino-style firmware for the host-build tests: a serial parser of a few commands, a hardware
// timer interrupt that raises a pin, sends a DAC value over SPI and lowers the pin, and a loop that sleeps
// one RTOS tick per pass.  Commands (one byte, then the payload):
//   'P' u16  timer period in µs          'V' u16  DAC code the interrupt sends
//   'E' u8   reply u8 + 1                 'C'      reply the interrupt count (u32, little-endian)
//   'W' u8   busy-wait u8 µs on a timer, then reply 'w'
//   'A' u8   n analogRead() calls, then reply 'a'
//   'H'      hang in a loop of calls that cost no time
#include <Arduino.h>
#include "tiny.h"

void setup() { tinyInit(); }

void loop() {
    tinyPoll();
    vTaskDelay(1);
}
