// A firmware for the delivered-pulse tests: each byte the host sends is one action on the eTactileKit's
// HV513 chain pins (BL 1, LE 2, POL 3, CLK 4, DIN 5) or its DAC, so random bytes drive the board through
// every combination the decoder has to follow.  Byte b: action b & 7, argument b >> 3.
//   0 CLK rising edge with DIN = arg & 1, then CLK low    4 DAC code arg << 4 (one SPI exchange)
//   1 LE = arg & 1        2 BL = arg & 1                  5 busy-wait arg us
//   3 POL = arg & 1       6 CLK = arg & 1 alone           7 DIN = arg & 1 alone
#include <Arduino.h>
#include <SPI.h>

void setup() {
    for (int pin = 1; pin <= 5; ++pin) pinMode(pin, OUTPUT);
    Serial.begin(921600);
    SPI.begin();
}

void loop() {
    while (Serial.available() > 0) {
        int b = Serial.read();
        int arg = b >> 3;
        switch (b & 7) {
            case 0:
                digitalWrite(5, arg & 1);
                digitalWrite(4, HIGH);
                digitalWrite(4, LOW);
                break;
            case 1: digitalWrite(2, arg & 1); break;
            case 2: digitalWrite(1, arg & 1); break;
            case 3: digitalWrite(3, arg & 1); break;
            case 4: SPI.transfer16((uint16_t)((arg << 4) << 2)); break;
            case 5: delayMicroseconds(arg); break;
            case 6: digitalWrite(4, arg & 1); break;
            default: digitalWrite(5, arg & 1); break;
        }
    }
    vTaskDelay(1);
}
