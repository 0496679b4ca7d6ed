/* fw_board_internal.h: what the core's modules share (not for targets). */
#ifndef FW_BOARD_INTERNAL_H
#define FW_BOARD_INTERNAL_H

#include "fw_board.h"
#include "fw_frame.h"

/* Frame and send one reply body on the serial link (counts frames_dropped if it cannot). */
void fw_send_tx(fw_board_t *b, const fw_tx_t *t);
void fw_send_error(fw_board_t *b, const char *code, const char *text, const char *arg, uint32_t arg_len);
void fw_set_decimation(fw_board_t *b, uint32_t k);
/* `E,NVM,...` for every slot neither erased nor valid (serial boards; at boot and after `I`). */
void fw_send_nvm_errors(fw_board_t *b);
/* Compensation as the per-sample path applies it (COMP on): the cubic SFEM of a version-2 record,
 * else eq. 13 then the constant SFEM (inline: no extra call on the per-sample path). */
static inline void fw_apply_comp(const fw_board_t *b, const fw_raw_sample_t *s, float temp_c, int32_t out[3])
{
    if (b->cubic.present) fw_compensate_cubic(&b->cubic, b->counts_per_g, s->acc, temp_c, out);
    else fw_compensate(&b->cal, b->id.ug_per_lsb, s->acc, temp_c, out);
}
/* Station commands by link. */
void fw_serial_command(fw_board_t *b, const uint8_t *body, uint32_t len);
void fw_can_command(fw_board_t *b, uint8_t dlc, const uint8_t *data);
/* One output sample (after decimation) on each link. */
void fw_serial_sample(fw_board_t *b, const fw_raw_sample_t *s);
void fw_can_sample(fw_board_t *b, const fw_raw_sample_t *s);
void fw_serial_segment(fw_board_t *b, const fw_segment_t *seg);
/* The pending long reply (fw_reply_t): format up to max_values more numbers; when none is left,
 * its tail, then frame and send it and clear pending. Nothing when none is pending. */
void fw_reply_step(fw_board_t *b, uint32_t max_values);

#endif
