// SPI stand-in: every transfer is one exchange in the virtual machine (its cost, its recorded event).
#pragma once
#include <cstdint>
#include "Arduino.h"

#define SPI_MODE0 0
#define SPI_MODE1 1
#define SPI_MODE2 2
#define SPI_MODE3 3
#define MSBFIRST 1
#define LSBFIRST 0
#define FSPI 0
#define HSPI 1

class SPISettings {
  public:
    SPISettings(uint32_t clock = 1000000, uint8_t bitOrder = MSBFIRST, uint8_t dataMode = SPI_MODE0)
        : clock(clock), bitOrder(bitOrder), dataMode(dataMode) {}
    uint32_t clock;
    uint8_t bitOrder;
    uint8_t dataMode;
};

class SPIClass {
  public:
    explicit SPIClass(uint8_t bus = FSPI) : bus_(bus) {}
    void begin(int8_t sck = -1, int8_t miso = -1, int8_t mosi = -1, int8_t ss = -1) {
        (void)sck; (void)miso; (void)mosi; (void)ss; hostbuild::point();
    }
    void end() {}
    void setFrequency(uint32_t freq) { (void)freq; hostbuild::point(); }
    void setDataMode(uint8_t mode) { (void)mode; hostbuild::point(); }
    void setBitOrder(uint8_t order) { (void)order; }
    void beginTransaction(SPISettings s) { (void)s; }
    void endTransaction() {}
    uint8_t transfer(uint8_t data) { return (uint8_t)hostbuild::spi_exchange(2 + bus_, data, 8); }
    uint16_t transfer16(uint16_t data) { return (uint16_t)hostbuild::spi_exchange(2 + bus_, data, 16); }
    uint32_t transfer32(uint32_t data) { return hostbuild::spi_exchange(2 + bus_, data, 32); }

  private:
    uint8_t bus_;
};
extern SPIClass SPI;
