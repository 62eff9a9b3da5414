// Arduino-ESP32 (core 2.x) stand-in for a host build of an eTactileKit firmware.
//
// Only what the firmware trees use is here; every call enters the virtual machine in hostbuild_shim.h,
// which charges its cost in virtual time.  Add a function by declaring it here (or in the header the
// firmware includes) and implementing it in hostbuild_runtime.cpp on top of the hostbuild:: primitives.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "hostbuild_shim.h"
#include "freertos/FreeRTOS.h"
#include "freertos/task.h"
#include "soc/gpio_struct.h"

#define IRAM_ATTR
#define DRAM_ATTR
#define ARDUINO 10819
#define ESP32 1

typedef uint8_t byte;
typedef bool boolean;

#define HIGH 0x1
#define LOW 0x0
#define INPUT 0x01
#define OUTPUT 0x03
#define PULLUP 0x04
#define INPUT_PULLUP 0x05
#define PULLDOWN 0x08
#define INPUT_PULLDOWN 0x09

#ifndef constrain
#define constrain(amt, low, high) ((amt) < (low) ? (low) : ((amt) > (high) ? (high) : (amt)))
#endif
using std::max;
using std::min;
using std::round;

inline void pinMode(uint8_t pin, uint8_t mode) { hostbuild::pin_mode(pin, mode); }
inline void digitalWrite(uint8_t pin, uint8_t val) { hostbuild::pin_write(pin, val ? 1 : 0); }
inline int digitalRead(uint8_t pin) { return hostbuild::pin_read(pin); }
inline uint16_t analogRead(uint8_t pin) { return (uint16_t)hostbuild::analog_read(pin); }

inline unsigned long micros() { return (unsigned long)(hostbuild::now_ns() / 1000); }
inline unsigned long millis() { return (unsigned long)(hostbuild::now_ns() / 1000000); }
inline void delay(uint32_t ms) { hostbuild::sleep_ns((int64_t)ms * 1000000); }
inline void delayMicroseconds(uint32_t us) { hostbuild::busy_wait_ns((int64_t)us * 1000); }
inline void yield() { hostbuild::sleep_ticks(0); }

// --- hardware timers (arduino-esp32 2.x API) ----------------------------------------------------------
typedef hostbuild::Timer hw_timer_t;
inline hw_timer_t* timerBegin(uint8_t num, uint16_t divider, bool countUp) {
    return hostbuild::timer_begin(num, divider, countUp);
}
inline void timerEnd(hw_timer_t* t) { hostbuild::timer_end(t); }
inline void timerAttachInterrupt(hw_timer_t* t, void (*fn)(void), bool edge) { hostbuild::timer_attach(t, fn, edge); }
inline void timerDetachInterrupt(hw_timer_t* t) { hostbuild::timer_detach(t); }
inline void timerAlarmWrite(hw_timer_t* t, uint64_t alarm_value, bool autoreload) {
    hostbuild::timer_alarm_write(t, alarm_value, autoreload);
}
inline void timerAlarmEnable(hw_timer_t* t) { hostbuild::timer_alarm_enable(t); }
inline void timerAlarmDisable(hw_timer_t* t) { hostbuild::timer_alarm_disable(t); }
inline bool timerAlarmEnabled(hw_timer_t* t) { return hostbuild::timer_alarm_enabled(t); }
inline void timerRestart(hw_timer_t* t) { hostbuild::timer_restart(t); }
inline void timerWrite(hw_timer_t* t, uint64_t val) { hostbuild::timer_write(t, val); }
inline uint64_t timerRead(hw_timer_t* t) { return hostbuild::timer_read(t); }
inline void timerStart(hw_timer_t* t) { hostbuild::timer_start(t); }
inline void timerStop(hw_timer_t* t) { hostbuild::timer_stop(t); }

// --- Serial ------------------------------------------------------------------------------------------
class HardwareSerial {
  public:
    void begin(unsigned long baud = 115200) { (void)baud; hostbuild::serial_begin(); }
    void end() {}
    size_t setRxBufferSize(size_t n) { hostbuild::serial_set_rx_buffer(n); return n; }
    int available() { return hostbuild::serial_available(); }
    int read() { return hostbuild::serial_read(); }
    size_t read(uint8_t* buf, size_t len) { return hostbuild::serial_read_buf(buf, len); }
    size_t readBytes(uint8_t* buf, size_t len) { return hostbuild::serial_read_buf(buf, len); }
    int peek() { return hostbuild::serial_peek(); }
    size_t write(uint8_t b) { return hostbuild::serial_write(&b, 1); }
    size_t write(const uint8_t* buf, size_t len) { return hostbuild::serial_write(buf, len); }
    size_t write(const char* s) { return hostbuild::serial_write((const uint8_t*)s, std::strlen(s)); }
    size_t print(const char* s) { return write(s); }
    size_t println(const char* s) { return write(s) + write("\r\n"); }
    void flush() {}
    operator bool() const { return true; }
};
extern HardwareSerial Serial;

// --- String (the little of it the firmware uses) -------------------------------------------------------
class String : public std::string {
  public:
    using std::string::string;
    String() = default;
    String(const std::string& s) : std::string(s) {}
    String(int v) : std::string(std::to_string(v)) {}
    String(unsigned v) : std::string(std::to_string(v)) {}
    String(long v) : std::string(std::to_string(v)) {}
    String(unsigned long v) : std::string(std::to_string(v)) {}
    const char* c_str() const { return std::string::c_str(); }
};
