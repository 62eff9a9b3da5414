// FreeRTOS task stand-in: vTaskDelay sleeps the (single) loop task in virtual time.
#pragma once
#include "freertos/FreeRTOS.h"
inline void vTaskDelay(TickType_t ticks) { hostbuild::sleep_ticks(ticks); }
