/* fw_board_internal.h: what the core's modules share (not for targets). */
#ifndef FW_BOARD_INTERNAL_H
#define FW_BOARD_INTERNAL_H

#include "fw_board.h"
#include "fw_frame.h"

/* Frame and send one reply body on the serial link (counts frames_dropped if it cannot). */
void fw_send_tx(fw_board_t *b, const fw_tx_t *t);
void fw_send_error(fw_board_t *b, const char *code, const char *text, const char *arg, uint32_t arg_len);
/* Decimation factor for a requested rate (drivers/sim/serial_pty._ratio in float64), 0 if the
 * rate does not divide the source rate. */
uint32_t fw_odr_ratio(double src_hz, double dst_hz);
void fw_set_decimation(fw_board_t *b, uint32_t k);
/* Station commands by link. */
void fw_serial_command(fw_board_t *b, const uint8_t *body, uint32_t len);
void fw_can_command(fw_board_t *b, uint8_t dlc, const uint8_t *data);
/* One output sample (after decimation) on each link. */
void fw_serial_sample(fw_board_t *b, const fw_raw_sample_t *s);
void fw_can_sample(fw_board_t *b, const fw_raw_sample_t *s);
void fw_serial_segment(fw_board_t *b, const fw_segment_t *seg);

#endif
