/* fw_boot.h: what a target tells the core about this start, and what the core tells the target
 * about its sensor (CONTRACT between core and targets, beside fw_hal.h).
 *
 * Why: recovery lives in the target (watchdog, fault handler, reset flags, sensor re-init), but the
 * station learns about it through the core's replies (design 3.1 identity `reset=`, `boots=`,
 * `fault=`, `fault_pc=`, `sensor_reinit=`; `E,SENSOR,...`). The target fills fw_boot_info_t from
 * its reset flags (RCC_CSR on silicon, a no-init RAM word on QEMU) and hands it over once, right
 * after fw_board_init.
 */
#ifndef FW_BOOT_H
#define FW_BOOT_H

#include <stdint.h>

typedef enum {
    FW_RESET_UNKNOWN = 0,
    FW_RESET_POWER = 1,
    FW_RESET_PIN = 2,
    FW_RESET_WATCHDOG = 3,
    FW_RESET_FAULT = 4,
    FW_RESET_BROWNOUT = 5,
    FW_RESET_SOFTWARE = 6
} fw_reset_cause_t;

typedef struct fw_boot_info {
    uint8_t cause;         /* fw_reset_cause_t */
    uint32_t boots;        /* starts since power-up: 1 after a power-on */
    uint32_t fault_cfsr;   /* cause FAULT: the stored CFSR (0 when none) */
    uint32_t fault_pc;     /* cause FAULT: the stacked PC of the faulting code */
} fw_boot_info_t;

struct fw_board;

/* The word the identity reply uses for a cause ("power", "watchdog", ...; "unknown" out of range). */
const char *fw_reset_word(uint8_t cause);
/* Once, right after fw_board_init: remembered for the identity reply (3.1) and frame 11 (3.2). */
void fw_board_set_boot(struct fw_board *b, const fw_boot_info_t *boot);
/* The target re-initialised a silent sensor (no data-ready within 3 periods while streaming) after
 * silent_ms: the core counts it (identity `sensor_reinit=`) and sends `E,SENSOR,...` (serial). */
void fw_board_sensor_reinit(struct fw_board *b, uint32_t silent_ms);
/* 1 while the station has the board streaming (the target's liveness check runs only then). */
int fw_board_streaming(const struct fw_board *b);
/* The output sample period in microseconds (source ODR / decimation): the liveness deadline is 3 of them. */
uint32_t fw_board_period_us(const struct fw_board *b);

/* Simulation fault (bridge `$X,selfcal_skew,<mg_per_c>`): the on-board calibrator's TDB result is
 * off by this much on every axis, a board whose calibrator disagrees with the station. */
void fw_board_selfcal_skew(struct fw_board *b, float tdb_mg_per_c);
/* The serial number of an STM32 board: "F4" + the 96-bit unique ID as 24 upper-case hex digits,
 * uid[0] first (design 3.1: unique by construction). out needs 27 bytes; returns the length (26). */
uint32_t fw_serial_from_uid(const uint8_t uid[12], char *out);

#endif
