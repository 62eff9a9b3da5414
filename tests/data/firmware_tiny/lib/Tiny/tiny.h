#ifndef TINY_H
#define TINY_H
#include <Arduino.h>
#include <SPI.h>

#define TINY_PIN 5            // the pin the interrupt raises and lowers
#define TINY_CS_PIN 40        // a second-bank pin (GPIO.out1_*) around the SPI exchange
#define TINY_RX_BUFFER 128    // the receive queue the firmware asks for
#define TINY_ADC_PIN 1        // the analog input the 'A' command reads

void tinyInit();
void tinyPoll();
#endif
