// The host build's virtual machine, as the Arduino/ESP32 stand-ins below see it.
//
// Every stand-in (GPIO register, SPI exchange, timer read, Serial call, vTaskDelay) enters the virtual
// machine through one of these functions: it charges the call's cost in virtual nanoseconds, lets a due
// timer interrupt run (the main loop is pre-empted only at such a call), records what the call did, and
// hands control back to Python when virtual time has reached the target Python asked for.
#pragma once
#include <cstddef>
#include <cstdint>

namespace hostbuild {

// GPIO output registers the firmware writes (w1ts sets bits, w1tc clears them).
enum GpioReg : int { OUT_W1TS = 0, OUT_W1TC = 1, OUT1_W1TS = 2, OUT1_W1TC = 3, OUT = 4, OUT1 = 5 };

void gpio_reg_write(int reg, uint32_t value);
uint32_t gpio_reg_read(int reg);
void pin_write(int pin, int level);
int pin_read(int pin);
void pin_mode(int pin, int mode);
int analog_read(int pin);

// One SPI exchange of `bits` bits on bus `bus`: returns what the device shifted back.
uint32_t spi_exchange(int bus, uint32_t out, int bits);

// Hardware timers (arduino-esp32 2.x semantics).
struct Timer;
Timer* timer_begin(int num, uint16_t divider, bool count_up);
void timer_end(Timer* t);
void timer_attach(Timer* t, void (*fn)(), bool edge);
void timer_detach(Timer* t);
void timer_alarm_write(Timer* t, uint64_t ticks, bool autoreload);
void timer_alarm_enable(Timer* t);
void timer_alarm_disable(Timer* t);
bool timer_alarm_enabled(Timer* t);
void timer_restart(Timer* t);
void timer_write(Timer* t, uint64_t ticks);
uint64_t timer_read(Timer* t);
void timer_start(Timer* t);
void timer_stop(Timer* t);

// Time.
int64_t now_ns();
void busy_wait_ns(int64_t ns);      // a busy-wait: interrupts still run, the loop stays busy
void sleep_ticks(uint32_t ticks);   // vTaskDelay: the loop sleeps until the n-th next RTOS tick
void sleep_ns(int64_t ns);          // delay(ms): the loop sleeps

// Serial (the USB CDC port the firmware talks through).
void serial_begin();
void serial_set_rx_buffer(size_t bytes);
int serial_available();
int serial_read();
size_t serial_read_buf(uint8_t* buf, size_t len);
int serial_peek();
size_t serial_write(const uint8_t* buf, size_t len);

// A shim call with no modelled cost (pinMode, SPI.begin): still a pre-emption point.
void point();

}  // namespace hostbuild
