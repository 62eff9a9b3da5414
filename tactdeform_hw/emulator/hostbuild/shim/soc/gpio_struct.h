// ESP32-S3 GPIO output registers as the firmware writes them (GPIO.out_w1ts = mask, GPIO.out1_w1ts.val).
// Each write goes through the virtual machine: it costs one GPIO write and is recorded per pin.
#pragma once
#include <cstdint>
#include "hostbuild_shim.h"

namespace hostbuild {
struct GpioRegister {
    int reg;
    GpioRegister& operator=(uint32_t v) { gpio_reg_write(reg, v); return *this; }
    operator uint32_t() const { return gpio_reg_read(reg); }
};
struct GpioRegister1 {
    GpioRegister val;
};
}  // namespace hostbuild

typedef struct gpio_dev_s {
    hostbuild::GpioRegister out{hostbuild::OUT};
    hostbuild::GpioRegister out_w1ts{hostbuild::OUT_W1TS};
    hostbuild::GpioRegister out_w1tc{hostbuild::OUT_W1TC};
    hostbuild::GpioRegister1 out1{{hostbuild::OUT1}};
    hostbuild::GpioRegister1 out1_w1ts{{hostbuild::OUT1_W1TS}};
    hostbuild::GpioRegister1 out1_w1tc{{hostbuild::OUT1_W1TC}};
} gpio_dev_t;
extern gpio_dev_t GPIO;
