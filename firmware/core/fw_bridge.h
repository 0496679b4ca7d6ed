/* fw_bridge.h: the sensor bridge (world simulator -> board), shared by the host and QEMU targets.
 *
 * Same framing as design 3.1 (`$BODY*HH\n`, so one codec parses it):
 *   `$B,<serial>,<sensor>,<ug_per_lsb>,<t_lsb_per_c>,<t_lsb_at_25c>,<odr_hz>*HH`  identity strap,
 *        first line: which sensor and serial this board carries (the target then calls
 *        fw_board_init and answers `$READY*HH\n` on the bridge);
 *   `$S,<t_us>,<ax>,<ay>,<az>,<t>*HH`  one sensor sample (data-ready: the target calls fw_sample).
 * Feed received bytes to a fw_linebuf_t (fw_frame.h) and each complete line to fw_bridge_line.
 */
#ifndef FW_BRIDGE_H
#define FW_BRIDGE_H

#include <stdint.h>
#include "fw_board.h"
#include "fw_frame.h"

#define FW_FW_VERSION_DEFAULT "fw-c-1.0"

typedef enum { FW_BRIDGE_NONE = 0, FW_BRIDGE_IDENTITY = 1, FW_BRIDGE_SAMPLE = 2 } fw_bridge_kind_t;

/* One line (without '\n'; a trailing '\r' is tolerated). Returns FW_BRIDGE_IDENTITY (id_out filled,
 * fw set to FW_FW_VERSION_DEFAULT), FW_BRIDGE_SAMPLE (s_out filled) or FW_BRIDGE_NONE (bad frame,
 * bad field, unknown type: skip it). t_us is taken modulo 2^32 (the board clock wraps). */
int fw_bridge_line(const uint8_t *line, uint32_t len, fw_identity_t *id_out, fw_raw_sample_t *s_out);
/* `$READY*HH\n` into out (cap >= 16); returns its length. */
uint32_t fw_bridge_ready(uint8_t *out, uint32_t cap);

#endif
