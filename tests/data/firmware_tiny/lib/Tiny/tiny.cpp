#include "tiny.h"

static hw_timer_t* stimTimer = NULL;   // 1 µs ticks (80 MHz / 80), drives the interrupt
static hw_timer_t* waitTimer = NULL;   // 1 µs ticks, for the busy-wait command
static volatile uint32_t isr_count = 0;
static volatile int dac_code = 0;
static uint32_t period_us = 700;
static uint8_t history[4] = {0, 0, 0, 0};   // the last four command bytes

static void IRAM_ATTR onTimer() {
    GPIO.out_w1ts = 1U << TINY_PIN;
    GPIO.out1_w1tc.val = 1U << (TINY_CS_PIN - 32);
    SPI.transfer16((uint16_t)(dac_code << 2));
    GPIO.out1_w1ts.val = 1U << (TINY_CS_PIN - 32);
    GPIO.out_w1tc = 1U << TINY_PIN;
    isr_count++;
}

void tinyInit() {
    pinMode(TINY_PIN, OUTPUT);
    Serial.setRxBufferSize(TINY_RX_BUFFER);
    Serial.begin(921600);
    SPI.begin(7, 8, 9);
    stimTimer = timerBegin(1, 80, true);
    waitTimer = timerBegin(0, 80, true);
    timerAttachInterrupt(stimTimer, &onTimer, true);
    timerAlarmWrite(stimTimer, period_us, true);
    timerAlarmEnable(stimTimer);
}

static int readByteBlocking() {
    while (Serial.available() < 1) {
    }
    return Serial.read();
}

static uint16_t readU16() {
    uint8_t b[2];
    while (Serial.available() < 2) {
    }
    Serial.read(b, 2);
    return (uint16_t)(b[0] | (b[1] << 8));
}

void tinyPoll() {
    static uint32_t polls = 0;  // a function-local static: the state map reads it through the symbol table
    ++polls;
    if (Serial.available() <= 0) return;
    int cmd = Serial.read();
    for (int i = 3; i > 0; --i) history[i] = history[i - 1];
    history[0] = (uint8_t)cmd;
    switch (cmd) {
        case 'P':
            period_us = readU16();
            timerAlarmDisable(stimTimer);
            timerAlarmWrite(stimTimer, period_us, true);
            timerAlarmEnable(stimTimer);
            break;
        case 'V': {
            int v = readU16();  // constrain() is a macro: it would read its argument more than once
            dac_code = constrain(v, 0, 4095);
            break;
        }
        case 'E': {
            uint8_t v = (uint8_t)(readByteBlocking() + 1);
            Serial.write(v);
            break;
        }
        case 'C': {
            uint32_t n = isr_count;
            uint8_t out[4] = {(uint8_t)n, (uint8_t)(n >> 8), (uint8_t)(n >> 16), (uint8_t)(n >> 24)};
            Serial.write(out, 4);
            break;
        }
        case 'W': {
            int us = readByteBlocking();
            timerRestart(waitTimer);
            while (timerRead(waitTimer) < (uint64_t)us) {
            }
            Serial.write('w');
            break;
        }
        case 'A': {  // u8 n: n analogRead() calls, then reply 'a'
            int n = readByteBlocking();
            int sum = 0;
            for (int i = 0; i < n; ++i) sum += analogRead(TINY_ADC_PIN);
            Serial.write(sum >= 0 ? 'a' : 'A');
            break;
        }
        case 'H':  // hang: a loop on a call that costs no time (the emulator must notice)
            for (;;) {
                pinMode(TINY_PIN, OUTPUT);
            }
        default:
            break;
    }
}
