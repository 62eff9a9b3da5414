// FreeRTOS stand-in: the types and the tick the firmware's main loop sleeps on.
#pragma once
#include <cstdint>
#include "hostbuild_shim.h"
typedef uint32_t TickType_t;
typedef int32_t BaseType_t;
typedef uint32_t UBaseType_t;
typedef void* TaskHandle_t;
#define portTICK_PERIOD_MS 1
#define pdMS_TO_TICKS(ms) ((TickType_t)(ms))
#define pdTRUE 1
#define pdFALSE 0
