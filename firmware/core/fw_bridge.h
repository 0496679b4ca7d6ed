/* fw_bridge.h: the sensor bridge (world simulator -> board), shared by the host and QEMU targets.
 *
 * Same framing as design 3.1 (`$BODY*HH\n`, so one codec parses it):
 *   `$B,<serial>,<sensor>,<ug_per_lsb>,<t_lsb_per_c>,<t_lsb_at_25c>,<odr_hz>*HH`  identity strap,
 *        first line: which sensor and serial this board carries (the target then calls
 *        fw_board_init and answers `$READY*HH\n` on the bridge);
 *   `$S,<t_us>,<ax>,<ay>,<az>,<t>*HH`  one sensor sample (data-ready: the target calls fw_sample);
 *   `$X,<fault>[,<value>]*HH`  fault injection, simulation only (this header is its
 *        contract; firmware/targets/qemu/README.md): `hardfault`, `hang`, `selfcal_skew,<mg_per_c>` (fw_bridge_fault).
 * Board -> simulator: `$READY*HH` (booted), `$BOOT*HH` (at a start: the simulator sends `$B` again;
 * a board that kept its identity across a reset answers `$READY`), `$INIT*HH` (the board
 * (re-)initialises its sensor: a simulated sensor that reset itself resumes only after this).
 * Feed received bytes to a fw_linebuf_t (fw_frame.h) and each complete line to fw_bridge_line (and,
 * when that says FW_BRIDGE_NONE, to fw_bridge_fault).
 */
#ifndef FW_BRIDGE_H
#define FW_BRIDGE_H

#include <stdint.h>
#include "fw_board.h"
#include "fw_frame.h"

#define FW_FW_VERSION_DEFAULT "fw-c-1.0"

typedef enum { FW_BRIDGE_NONE = 0, FW_BRIDGE_IDENTITY = 1, FW_BRIDGE_SAMPLE = 2, FW_BRIDGE_FAULT = 3 } fw_bridge_kind_t;

typedef enum {
    FW_FAULT_NONE = 0,
    FW_FAULT_HARDFAULT = 1,      /* execute an undefined instruction */
    FW_FAULT_HANG = 2,           /* the main loop stops (and so stops feeding the watchdog) */
    FW_FAULT_SELFCAL_SKEW = 3    /* fw_board_selfcal_skew(value) */
} fw_fault_kind_t;

typedef struct fw_bridge_fault {
    uint8_t kind;    /* fw_fault_kind_t */
    float value;     /* FW_FAULT_SELFCAL_SKEW: mg/C (finite) */
} fw_bridge_fault_t;

/* One line (without '\n'; a trailing '\r' is tolerated). Returns FW_BRIDGE_IDENTITY (id_out filled,
 * fw set to FW_FW_VERSION_DEFAULT), FW_BRIDGE_SAMPLE (s_out filled) or FW_BRIDGE_NONE (bad frame,
 * bad field, unknown type: skip it). t_us is taken modulo 2^32 (the board clock wraps). */
int fw_bridge_line(const uint8_t *line, uint32_t len, fw_identity_t *id_out, fw_raw_sample_t *s_out);
/* `$X,...` fault injection: FW_BRIDGE_FAULT (out filled) or FW_BRIDGE_NONE (not one, or bad). */
int fw_bridge_fault(const uint8_t *line, uint32_t len, fw_bridge_fault_t *out);
/* `$READY*HH\n`, `$BOOT*HH\n`, `$INIT*HH\n` into out (cap >= 16); return the length (0: no room). */
uint32_t fw_bridge_ready(uint8_t *out, uint32_t cap);
uint32_t fw_bridge_boot(uint8_t *out, uint32_t cap);
uint32_t fw_bridge_init(uint8_t *out, uint32_t cap);

#endif
