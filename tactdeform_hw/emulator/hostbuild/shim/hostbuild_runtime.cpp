// The host build's virtual machine: virtual time, the firmware as a coroutine, the timers, GPIO, SPI and
// Serial stand-ins, and the extern "C" interface Python drives through ctypes.
//
// The firmware's setup()/loop() run on their own stack (ucontext).  Python asks for a target time with
// hb_run_until(); the firmware runs until a shim call finds virtual time at or past the target, then
// control returns to Python with the firmware suspended inside that call.  Between shim calls firmware
// code costs no virtual time.  A timer interrupt pre-empts the main loop at its alarm's exact time inside
// a call's work (an idle wait — vTaskDelay, delay, a busy-wait —, an analogRead, a Serial call), and at
// the next shim call otherwise (a GPIO write, 50 ns; an SPI exchange, which the upstream eTactileKit
// firmwares make only in their interrupt handler's pulses).  A Serial read takes its bytes
// from the queue as it starts, so an interrupt inside it comes before the firmware stores them.
#include <ucontext.h>

#include <climits>
#include <deque>
#include <vector>

#include "Arduino.h"
#include "SPI.h"
#include "soc/spi_struct.h"

HardwareSerial Serial;
SPIClass SPI;
gpio_dev_t GPIO;
spi_dev_t GPSPI2(2);
spi_dev_t GPSPI3(3);

void setup();
void loop();

namespace hostbuild {

// Costs in virtual nanoseconds, set by Python from its TimingModel (hb_configure's order).
enum Cost {
    C_SPI, C_GPIO, C_ISR_ENTRY, C_ISR_EXIT, C_AVAILABLE, C_READ_BYTE, C_ANALOG, C_RTOS_TICK, C_TICK_PHASE,
    C_APB_PS, C_RX_DEFAULT, C_STALL_LIMIT, C_COUNT
};
static int64_t cost[C_COUNT] = {6600, 50, 2000, 0, 2000, 1000, 20000, 1000000, 0, 12500, 256, 50000000};

enum Kind {
    EV_GPIO = 1, EV_SPI = 2, EV_ISR_ENTER = 3, EV_ISR_RETURN = 4, EV_ALARM_ENABLE = 5, EV_ALARM_DISABLE = 6,
    EV_TX = 7, EV_RX_DROP = 8, EV_ALARM_WRITE = 9, EV_TIMER_RESTART = 10
};
struct Event {
    int64_t t_ns;
    int32_t kind;
    int32_t a;
    int64_t b;
    int64_t c;
};
static std::vector<Event> events;

// --- the board: the HV513 chain and the DAC, decoded into delivered pulses ------------------------------
// The same decoding as the package's delivered.ChainDecoder (its reference), run here on every pin and DAC
// event as it is recorded: DIN is shifted in on each CLK rising edge, the outputs follow the shift register
// while LE is high, nothing flows while BL is low or the DAC code is 0, and a stretch of current ends at any
// change of the code, the outputs, the polarity or BL.
struct DeliveredRecord {
    int64_t start_ns;
    int64_t end_ns;
    int32_t code;
    int32_t polarity;
    int64_t n_outputs;  // its outputs are the next n_outputs entries of delivered_outputs
};
enum BoardPin { BP_BL, BP_LE, BP_POL, BP_CLK, BP_DIN, BP_COUNT };
static int board_pin[BP_COUNT] = {1, 2, 3, 4, 5};
static uint64_t board_pin_mask = 0x3EULL;  // the pins the decoder follows
static int board_level[64] = {0};
static int64_t board_dac_at_ns = 0;
static int32_t board_code = 0;
static std::vector<uint8_t> chain_shift, chain_latched;
static bool open_flowing = false;
static int64_t open_start_ns = 0;
static int32_t open_code = 0, open_polarity = 0;
static std::vector<uint8_t> open_latched;
static std::vector<DeliveredRecord> delivered;
static std::vector<int32_t> delivered_outputs;

static bool board_flowing() {
    if (board_code <= 0 || !board_level[board_pin[BP_BL]]) return false;
    for (uint8_t bit : chain_latched)
        if (bit) return true;
    return false;
}
static void board_update(int64_t t_ns) {
    bool flowing = board_flowing();
    int32_t pol = board_level[board_pin[BP_POL]];
    if (open_flowing &&
        (!flowing || board_code != open_code || pol != open_polarity || chain_latched != open_latched)) {
        if (t_ns > open_start_ns) {
            int64_t n = 0;
            for (size_t i = 0; i < open_latched.size(); ++i)
                if (open_latched[i]) {
                    delivered_outputs.push_back((int32_t)i);
                    ++n;
                }
            delivered.push_back({open_start_ns, t_ns, open_code, open_polarity, n});
        }
        open_flowing = false;
    }
    if (flowing && !open_flowing) {
        open_flowing = true;
        open_start_ns = t_ns;
        open_code = board_code;
        open_polarity = pol;
        open_latched = chain_latched;
    }
}
static void board_gpio(int64_t t_ns, int pin, int level) {
    if (pin < 0 || pin >= 64 || !(board_pin_mask & (1ULL << pin))) return;
    if (pin == board_pin[BP_CLK] && level && !board_level[pin] && !chain_shift.empty()) {
        std::memmove(chain_shift.data() + 1, chain_shift.data(), chain_shift.size() - 1);
        chain_shift[0] = (uint8_t)board_level[board_pin[BP_DIN]];
    }
    board_level[pin] = level;
    if (board_level[board_pin[BP_LE]]) chain_latched = chain_shift;
    board_update(t_ns);
}
static void board_dac(int64_t t_ns, int32_t code) {
    board_code = code;
    board_update(t_ns);
}

static bool record_pins = true;  // keep pin and SPI events too (they are decoded either way)
static void record(int64_t t, int kind, int a, int64_t b, int64_t c) {
    if (kind == EV_GPIO) {
        board_gpio(t, a, (int)b);
        if (!record_pins) return;
    } else if (kind == EV_SPI) {
        board_dac(t + board_dac_at_ns, (int32_t)((b >> 2) & 0xFFF));
        if (!record_pins) return;
    }
    events.push_back({t, kind, a, b, c});
}

// Firmware variables read at every interrupt's entry (the generated accessor unit's getters, registered
// from Python): a scan uses the values the main loop left, which cannot change until the handler returns,
// so one reading per entry says exactly what every pulse of the scan was made from.  Only changes are kept.
typedef double (*Getter)(int);
struct Watch {
    Getter get;
    int index;
    double last;
    bool seen;
};
struct Sample {
    int64_t t_ns;
    int64_t slot;
    double value;
};
static std::vector<Watch> watches;
static std::vector<Sample> samples;
static void sample_watches(int64_t t) {
    for (size_t i = 0; i < watches.size(); ++i) {
        Watch& w = watches[i];
        double v = w.get(w.index);
        if (!w.seen || v != w.last) {
            samples.push_back({t, (int64_t)i, v});
            w.last = v;
            w.seen = true;
        }
    }
}

static const int64_t NEVER = INT64_MAX;
static int64_t now = 0;
static int64_t target = 0;
static int status = 0;  // 0 running, 1 stalled (calls without time passing), 2 no memory for the stack,
                        // 3 released (hb_release)
static bool in_isr = false;
static bool interrupts_enabled = true;
static int64_t stall_calls = 0;
static int64_t stall_at = -1;
static bool released = false;  // hb_release ran: a shim call (a static destructor's) returns at once

// --- the coroutine ------------------------------------------------------------------------------------
static ucontext_t host_ctx, fw_ctx;
static char* fw_stack = nullptr;  // malloc'd, not zeroed: pages the firmware never touches cost nothing
static const size_t FW_STACK_BYTES = 1 << 20;
static bool started = false;

static void fw_main() {
    setup();
    for (;;) loop();
}
static void to_host() { swapcontext(&fw_ctx, &host_ctx); }

// --- timers -------------------------------------------------------------------------------------------
struct Timer {
    int num = 0;
    int64_t tick_ps = 500000;
    bool running = true;
    int64_t base_ns = 0;      // when the counter held base_count
    uint64_t base_count = 0;
    uint64_t alarm = 0;
    bool autoreload = false;
    bool alarm_en = false;
    void (*isr)() = nullptr;
    int64_t due_ns = NEVER;
};
static Timer timers[4];
static bool timer_used[4] = {false, false, false, false};

static uint64_t counter_at(const Timer* t, int64_t at) {
    if (!t->running) return t->base_count;
    return t->base_count + (uint64_t)(((at - t->base_ns) * 1000) / t->tick_ps);
}
static void recompute_due(Timer* t) {
    if (!t->alarm_en || !t->isr || !t->running) {
        t->due_ns = NEVER;
        return;
    }
    uint64_t c = counter_at(t, now);
    if (t->alarm <= c) {  // an alarm the counter has already passed fires at once
        t->due_ns = now;
        return;
    }
    int64_t ticks = (int64_t)(t->alarm - t->base_count);
    t->due_ns = t->base_ns + (ticks * t->tick_ps + 999) / 1000;
}
static Timer* next_due_timer() {
    Timer* best = nullptr;
    for (int i = 0; i < 4; ++i)
        if (timer_used[i] && timers[i].due_ns != NEVER && (!best || timers[i].due_ns < best->due_ns))
            best = &timers[i];
    return best;
}
static int64_t next_due() {
    if (in_isr || !interrupts_enabled) return NEVER;
    Timer* t = next_due_timer();
    return t ? t->due_ns : NEVER;
}

// --- Serial receive path ------------------------------------------------------------------------------
struct Packet {
    int64_t t_ns;
    int64_t host_offset;
    std::vector<uint8_t> data;
};
static std::deque<Packet> rx_pending;
static std::deque<uint8_t> rx_queue;
static size_t rx_capacity = 256;
// false: the firmware's reads find nothing (a main loop that stopped reading; the queue still fills)
static bool reading = true;
static int64_t rx_dropped = 0;

static void admit_rx() {
    while (!rx_pending.empty() && rx_pending.front().t_ns <= now) {
        Packet& p = rx_pending.front();
        for (size_t i = 0; i < p.data.size(); ++i) {
            if (rx_queue.size() >= rx_capacity) {  // the rest of the packet is discarded
                int64_t n = (int64_t)(p.data.size() - i);
                rx_dropped += n;
                record(p.t_ns, EV_RX_DROP, (int)n, p.host_offset + (int64_t)i, (int64_t)rx_queue.size());
                break;
            }
            rx_queue.push_back(p.data[i]);
        }
        rx_pending.pop_front();
    }
}
static int64_t next_arrival() { return rx_pending.empty() ? NEVER : rx_pending.front().t_ns; }

// --- pre-emption points -------------------------------------------------------------------------------
static void run_isr(Timer* t);

static void run_due_isrs() {
    for (;;) {
        int64_t d = next_due();
        if (d == NEVER || d > now) return;
        run_isr(next_due_timer());
    }
}

// Every shim call starts here: arrivals up to now enter the queue, a due interrupt runs, and the firmware
// is suspended while virtual time is at or past Python's target.
static void enter() {
    if (released) return;
    if (now == stall_at) {
        if (++stall_calls > cost[C_STALL_LIMIT]) {
            status = 1;
            to_host();
        }
    } else {
        stall_at = now;
        stall_calls = 0;
    }
    admit_rx();
    run_due_isrs();
    while (now >= target) {
        to_host();
        admit_rx();
        run_due_isrs();
    }
}

// Let virtual time pass up to `end` (a sleep or a busy-wait): interrupts run at their alarm's exact
// time, and the firmware is suspended at Python's target.
static void wait_until(int64_t end) {
    if (released) return;
    for (;;) {
        admit_rx();
        int64_t next = end;
        int64_t d = next_due();
        if (d < next) next = d;
        if (next > target) {
            if (now < target) now = target;
            to_host();
            continue;
        }
        if (next > now) now = next;
        if (next_due() <= now) {
            run_due_isrs();
            continue;
        }
        if (now >= end) return;
    }
}

// Spend `ns` of the firmware's own work inside a call (a conversion, the serial driver's bookkeeping): a
// due interrupt pre-empts it at its alarm's exact time, as the chip takes it, and the rest of the work
// follows the handler.
static void spend(int64_t ns) {
    int64_t left = ns;
    for (;;) {
        int64_t d = next_due();
        if (d == NEVER || d >= now + left) break;
        if (d > now) {
            left -= d - now;
            now = d;
        }
        run_due_isrs();
    }
    now += left;
}

static void run_isr(Timer* t) {
    int64_t fired = t->due_ns;
    if (t->autoreload) {  // the hardware reloads the counter at the alarm
        t->base_ns = fired;
        t->base_count = 0;
        recompute_due(t);
    } else {
        t->alarm_en = false;
        t->due_ns = NEVER;
    }
    in_isr = true;
    record(now, EV_ISR_ENTER, t->num, fired, 0);
    sample_watches(now);
    now += cost[C_ISR_ENTRY];
    t->isr();
    now += cost[C_ISR_EXIT];
    record(now, EV_ISR_RETURN, t->num, fired, 0);
    in_isr = false;
    recompute_due(t);
}

// --- the stand-ins ------------------------------------------------------------------------------------
static uint64_t pin_level = 0;
static int analog_value[64] = {0};
static const Timer* last_poll = nullptr;  // the timer of an immediately repeated timerRead

void point() {
    enter();
    last_poll = nullptr;
}

static void write_pins(uint64_t mask, int level) {
    int64_t t = now + cost[C_GPIO];
    for (int pin = 0; pin < 64; ++pin) {
        if (mask & (1ULL << pin)) {
            record(t, EV_GPIO, pin, level, 0);
            if (level) pin_level |= 1ULL << pin; else pin_level &= ~(1ULL << pin);
        }
    }
    now = t;
}

void gpio_reg_write(int reg, uint32_t value) {
    point();
    switch (reg) {
        case OUT_W1TS: write_pins(value, 1); break;
        case OUT_W1TC: write_pins(value, 0); break;
        case OUT1_W1TS: write_pins((uint64_t)value << 32, 1); break;
        case OUT1_W1TC: write_pins((uint64_t)value << 32, 0); break;
        case OUT: {
            uint64_t mask = 0xFFFFFFFFULL;
            uint64_t on = value, off = (~(uint64_t)value) & mask;
            int64_t t = now + cost[C_GPIO];
            for (int pin = 0; pin < 32; ++pin)
                if ((on | off) & (1ULL << pin)) record(t, EV_GPIO, pin, (on >> pin) & 1, 0);
            pin_level = (pin_level & ~mask) | on;
            now = t;
            break;
        }
        case OUT1: {
            uint64_t mask = 0xFFFFFFFFULL << 32;
            uint64_t on = (uint64_t)value << 32;
            int64_t t = now + cost[C_GPIO];
            for (int pin = 32; pin < 64; ++pin) record(t, EV_GPIO, pin, (on >> pin) & 1, 0);
            pin_level = (pin_level & ~mask) | on;
            now = t;
            break;
        }
        default: break;
    }
}
uint32_t gpio_reg_read(int reg) {
    point();
    if (reg == OUT1 || reg == OUT1_W1TS || reg == OUT1_W1TC) return (uint32_t)(pin_level >> 32);
    return (uint32_t)pin_level;
}
void pin_write(int pin, int level) {
    point();
    if (pin >= 0 && pin < 64) write_pins(1ULL << pin, level);
}
int pin_read(int pin) {
    point();
    return (pin >= 0 && pin < 64) ? (int)((pin_level >> pin) & 1) : 0;
}
void pin_mode(int pin, int mode) {
    (void)pin;
    (void)mode;
    point();
}
int analog_read(int pin) {
    point();
    spend(cost[C_ANALOG]);
    return (pin >= 0 && pin < 64) ? analog_value[pin] : 0;
}

// The device on the bus: the eTactileKit's DAC and ADC share the exchange, and the ADC returns what the
// DAC held when the exchange started (the outgoing word of the previous exchange): an echo.
static uint32_t spi_last_out[4] = {0, 0, 0, 0};
uint32_t spi_exchange(int bus, uint32_t out, int bits) {
    point();
    int b = bus & 3;
    uint32_t back = spi_last_out[b];
    record(now, EV_SPI, bus, out, back);
    spi_last_out[b] = out;
    now += cost[C_SPI];
    (void)bits;
    return back;
}

Timer* timer_begin(int num, uint16_t divider, bool count_up) {
    point();
    (void)count_up;
    int i = num & 3;
    Timer* t = &timers[i];
    *t = Timer();
    t->num = num;
    t->tick_ps = (int64_t)(divider ? divider : 65536) * cost[C_APB_PS];
    t->base_ns = now;
    timer_used[i] = true;
    return t;
}
void timer_end(Timer* t) {
    point();
    timer_used[t->num & 3] = false;
    t->due_ns = NEVER;
}
void timer_attach(Timer* t, void (*fn)(), bool edge) {
    point();
    (void)edge;
    t->isr = fn;
    recompute_due(t);
}
void timer_detach(Timer* t) {
    point();
    t->isr = nullptr;
    recompute_due(t);
}
void timer_alarm_write(Timer* t, uint64_t ticks, bool autoreload) {
    point();
    t->alarm = ticks;
    t->autoreload = autoreload;
    record(now, EV_ALARM_WRITE, t->num, (int64_t)ticks, autoreload);
    recompute_due(t);
}
void timer_alarm_enable(Timer* t) {
    point();
    t->alarm_en = true;
    record(now, EV_ALARM_ENABLE, t->num, 0, 0);
    recompute_due(t);
}
void timer_alarm_disable(Timer* t) {
    point();
    t->alarm_en = false;
    record(now, EV_ALARM_DISABLE, t->num, 0, 0);
    recompute_due(t);
}
bool timer_alarm_enabled(Timer* t) {
    point();
    return t->alarm_en;
}
void timer_restart(Timer* t) {
    point();
    t->base_ns = now;
    t->base_count = 0;
    recompute_due(t);
}
void timer_write(Timer* t, uint64_t ticks) {
    point();
    t->base_ns = now;
    t->base_count = ticks;
    recompute_due(t);
}
void timer_start(Timer* t) {
    point();
    if (!t->running) {
        t->running = true;
        t->base_ns = now;
    }
    recompute_due(t);
}
void timer_stop(Timer* t) {
    point();
    if (t->running) {
        t->base_count = counter_at(t, now);
        t->running = false;
    }
    recompute_due(t);
}
// A busy-wait polls the counter: an immediately repeated read of the same timer happens at the next tick.
uint64_t timer_read(Timer* t) {
    bool repeated = (last_poll == t);
    point();
    if (repeated && t->running) {
        uint64_t c = counter_at(t, now);
        int64_t next = t->base_ns + (int64_t)(((c + 1 - t->base_count) * t->tick_ps + 999) / 1000);
        wait_until(next);
    }
    last_poll = t;
    return counter_at(t, now);
}

int64_t now_ns() {
    point();
    return now;
}
void busy_wait_ns(int64_t ns) {
    point();
    wait_until(now + ns);
}
void sleep_ns(int64_t ns) {
    point();
    wait_until(now + ns);
}
void sleep_ticks(uint32_t ticks) {
    point();
    if (ticks == 0) return;
    int64_t tick = cost[C_RTOS_TICK], phase = cost[C_TICK_PHASE];
    int64_t k = (now - phase) >= 0 ? (now - phase) / tick + 1 : 0;
    wait_until(phase + (k + (int64_t)ticks - 1) * tick);
}

void serial_begin() { point(); }
void serial_set_rx_buffer(size_t bytes) {
    point();
    if (bytes > 0) rx_capacity = bytes;
}
int serial_available() {
    point();
    int n = reading ? (int)rx_queue.size() : 0;
    spend(cost[C_AVAILABLE]);
    return n;
}
int serial_read() {
    point();
    int v = -1;
    if (!rx_queue.empty() && reading) {
        v = rx_queue.front();
        rx_queue.pop_front();
    }
    spend(cost[C_READ_BYTE]);
    return v;
}
size_t serial_read_buf(uint8_t* buf, size_t len) {
    point();
    size_t n = 0;
    while (reading && n < len && !rx_queue.empty()) {
        buf[n++] = rx_queue.front();
        rx_queue.pop_front();
    }
    spend(cost[C_READ_BYTE] * (int64_t)n);
    return n;
}
int serial_peek() {
    point();
    return rx_queue.empty() || !reading ? -1 : rx_queue.front();
}
size_t serial_write(const uint8_t* buf, size_t len) {
    point();
    for (size_t i = 0; i < len; ++i) record(now, EV_TX, buf[i], 0, 0);
    return len;
}

}  // namespace hostbuild

// --- the interface Python drives ------------------------------------------------------------------------
using namespace hostbuild;

extern "C" {

int hb_configure(const int64_t* values, int n) {
    if (n != C_COUNT) return -1;
    for (int i = 0; i < n; ++i) cost[i] = values[i];
    rx_capacity = (size_t)cost[C_RX_DEFAULT];
    return 0;
}
void hb_set_analog(int pin, int value) {
    if (pin >= 0 && pin < 64) analog_value[pin] = value;
}
void hb_set_interrupts(int enabled) { interrupts_enabled = enabled != 0; }
void hb_set_reading(int enabled) { reading = enabled != 0; }

int hb_run_until(int64_t t_ns) {
    if (status) return status;  // 3: released
    target = t_ns;
    if (!started) {
        started = true;
        fw_stack = static_cast<char*>(std::malloc(FW_STACK_BYTES));
        if (!fw_stack) return 2;
        getcontext(&fw_ctx);
        fw_ctx.uc_stack.ss_sp = fw_stack;
        fw_ctx.uc_stack.ss_size = FW_STACK_BYTES;
        fw_ctx.uc_link = &host_ctx;
        makecontext(&fw_ctx, fw_main, 0);
    }
    swapcontext(&host_ctx, &fw_ctx);
    return status;
}
int64_t hb_now() { return now; }

void hb_rx_push(const uint8_t* data, int64_t n, int64_t t_ns, int64_t host_offset) {
    Packet p;
    p.t_ns = t_ns;
    p.host_offset = host_offset;
    p.data.assign(data, data + n);
    rx_pending.push_back(std::move(p));
}
int64_t hb_rx_queued() { return (int64_t)rx_queue.size(); }
int64_t hb_rx_in_flight() {
    int64_t n = 0;
    for (const Packet& p : rx_pending) n += (int64_t)p.data.size();
    return n;
}
int64_t hb_rx_capacity() { return (int64_t)rx_capacity; }
int64_t hb_rx_dropped() { return rx_dropped; }

int64_t hb_event_count() { return (int64_t)events.size(); }
int64_t hb_events_take(Event* dst, int64_t max) {
    int64_t n = std::min<int64_t>(max, (int64_t)events.size());
    if (n > 0) {
        std::memcpy(dst, events.data(), sizeof(Event) * (size_t)n);
        events.erase(events.begin(), events.begin() + n);
    }
    return n;
}

// exists, alarm ticks, autoreload, alarm enabled, has an interrupt handler, tick in ps, counter now
int hb_timer_info(int num, int64_t* out) {
    int i = num & 3;
    if (!timer_used[i]) return 0;
    const Timer* t = &timers[i];
    out[0] = (int64_t)t->alarm;
    out[1] = t->autoreload;
    out[2] = t->alarm_en;
    out[3] = t->isr != nullptr;
    out[4] = t->tick_ps;
    out[5] = (int64_t)counter_at(t, now);
    out[6] = t->due_ns == NEVER ? -1 : t->due_ns;
    return 1;
}
int64_t hb_pin_levels() { return (int64_t)pin_level; }

// The board the decoder models: `outputs` HV513 outputs, the DAC taking effect `dac_at_ns` into an SPI
// exchange, and the pins (BL, LE, POL, CLK, DIN) in `pins`.  Call before the first hb_run_until.
int hb_board_configure(int64_t outputs, int64_t dac_at_ns, const int* pins) {
    if (outputs < 0) return -1;
    uint64_t mask = 0;
    for (int i = 0; i < BP_COUNT; ++i) {
        if (pins[i] < 0 || pins[i] >= 64) return -1;
        board_pin[i] = pins[i];
        mask |= 1ULL << pins[i];
    }
    board_pin_mask = mask;
    board_dac_at_ns = dac_at_ns;
    chain_shift.assign((size_t)outputs, 0);
    chain_latched.assign((size_t)outputs, 0);
    return 0;
}
void hb_set_record_pins(int enabled) { record_pins = enabled != 0; }
int64_t hb_delivered_count() { return (int64_t)delivered.size(); }
int64_t hb_delivered_outputs_count() { return (int64_t)delivered_outputs.size(); }
// Moves every pulse delivered so far out: `records` and `outputs` must hold hb_delivered_count() and
// hb_delivered_outputs_count() entries.
int64_t hb_delivered_take(DeliveredRecord* records, int32_t* outputs) {
    int64_t n = (int64_t)delivered.size();
    if (n > 0) std::memcpy(records, delivered.data(), sizeof(DeliveredRecord) * (size_t)n);
    if (!delivered_outputs.empty())
        std::memcpy(outputs, delivered_outputs.data(), sizeof(int32_t) * delivered_outputs.size());
    delivered.clear();
    delivered_outputs.clear();
    return n;
}

// Frees what the firmware's run holds outside the library's own data (its stack, the event buffers), so
// the library can be unloaded: after it the firmware cannot be run again.
void hb_release() {
    released = true;
    status = 3;
    std::free(fw_stack);
    fw_stack = nullptr;
    std::vector<Event>().swap(events);
    std::vector<DeliveredRecord>().swap(delivered);
    std::vector<int32_t>().swap(delivered_outputs);
    rx_pending.clear();
    rx_queue.clear();
}
int hb_in_isr() { return in_isr ? 1 : 0; }

int64_t hb_watch_add(void* getter, int index) {
    watches.push_back({reinterpret_cast<Getter>(getter), index, 0.0, false});
    return (int64_t)watches.size() - 1;
}
int64_t hb_sample_count() { return (int64_t)samples.size(); }
int64_t hb_samples_take(Sample* dst, int64_t max) {
    int64_t n = std::min<int64_t>(max, (int64_t)samples.size());
    if (n > 0) {
        std::memcpy(dst, samples.data(), sizeof(Sample) * (size_t)n);
        samples.erase(samples.begin(), samples.begin() + n);
    }
    return n;
}

}  // extern "C"
