// ESP32-S3 general-purpose SPI (GPSPI2) registers as a firmware that drives the bus directly uses them:
// the bit length, the data buffer, and the update/usr command bits.  Writing cmd.usr = 1 performs one
// exchange in the virtual machine (its cost, its recorded event); the hardware clears the bit when the
// exchange is done, so a firmware's `while (GPSPI2.cmd.usr);` reads 0 at once.  The data buffer holds the
// bytes in wire order (first byte sent in the low byte), as on the chip.
#pragma once
#include <cstdint>
#include "hostbuild_shim.h"

namespace hostbuild {
struct SpiDev;
struct SpiUsrBit {
    SpiDev* dev;
    SpiUsrBit& operator=(uint32_t v);
    operator uint32_t() const { point(); return 0; }
};
struct SpiUpdateBit {
    SpiUpdateBit& operator=(uint32_t v) { (void)v; point(); return *this; }
    operator uint32_t() const { point(); return 0; }
};
struct SpiCmd {
    SpiUpdateBit update;
    SpiUsrBit usr;
};
struct SpiDlen {
    uint32_t ms_data_bitlen = 7;
};
struct SpiDev {
    SpiDlen ms_dlen;
    uint32_t data_buf[16] = {0};
    SpiCmd cmd{{}, {this}};
    int bus;
    explicit SpiDev(int b) : bus(b) {}
};
inline SpiUsrBit& SpiUsrBit::operator=(uint32_t v) {
    if (v) {
        int bits = (int)dev->ms_dlen.ms_data_bitlen + 1;
        if (bits > 32) bits = 32;
        int nbytes = (bits + 7) / 8;
        uint32_t wire = 0;
        for (int i = 0; i < nbytes; ++i) wire = (wire << 8) | ((dev->data_buf[0] >> (8 * i)) & 0xFF);
        uint32_t back = spi_exchange(dev->bus, wire, bits);
        uint32_t buf = 0;
        for (int i = 0; i < nbytes; ++i) buf |= ((back >> (8 * (nbytes - 1 - i))) & 0xFF) << (8 * i);
        dev->data_buf[0] = buf;
    } else {
        point();
    }
    return *this;
}
}  // namespace hostbuild

typedef hostbuild::SpiDev spi_dev_t;
extern spi_dev_t GPSPI2;
extern spi_dev_t GPSPI3;
