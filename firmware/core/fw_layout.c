/* fw_layout.c: sizes and offsets of the core's structs, by name, for the ctypes mirrors in tests/.
 *
 * Why: a ctypes mirror that silently disagrees with the C layout reads garbage or writes past the
 * board (a segfault at best). The tests compare every mirror with what the compiler laid out, so a
 * changed struct fails with the field's name. Not on any target's path (--gc-sections drops it). */
#include <stddef.h>
#include "fw_board.h"

typedef struct layout_entry { const char *name; uint32_t value; } layout_entry_t;

#define SIZE(t) { #t, (uint32_t)sizeof(t) }
#define OFF(t, f) { #t "." #f, (uint32_t)offsetof(t, f) }

static const layout_entry_t LAYOUT[] = {
    SIZE(fw_identity_t), SIZE(fw_cal_t), SIZE(fw_cubic_t), SIZE(fw_hal_t), SIZE(fw_raw_sample_t),
    SIZE(fw_boot_info_t), SIZE(fw_tx_t), SIZE(fw_reply_t), SIZE(fw_selfcal_t), SIZE(fw_board_t),
    OFF(fw_identity_t, serial), OFF(fw_identity_t, sensor), OFF(fw_identity_t, fw), OFF(fw_identity_t, ug_per_lsb),
    OFF(fw_identity_t, t_lsb_per_c), OFF(fw_identity_t, t_lsb_at_25c), OFF(fw_identity_t, odr_hz),
    OFF(fw_cal_t, thermal), OFF(fw_cal_t, sfem), OFF(fw_cal_t, thermal_crc), OFF(fw_cal_t, sfem_crc),
    OFF(fw_cal_t, has_sfem), OFF(fw_cal_t, comp),
    OFF(fw_cubic_t, t_ref_c), OFF(fw_cubic_t, t_lo_c), OFF(fw_cubic_t, t_hi_c), OFF(fw_cubic_t, c),
    OFF(fw_cubic_t, crc), OFF(fw_cubic_t, present),
    OFF(fw_boot_info_t, cause), OFF(fw_boot_info_t, boots), OFF(fw_boot_info_t, fault_cfsr),
    OFF(fw_boot_info_t, fault_pc),
    OFF(fw_tx_t, body), OFF(fw_tx_t, len), OFF(fw_tx_t, overflow),
    OFF(fw_reply_t, tx), OFF(fw_reply_t, vals), OFF(fw_reply_t, tail_u32), OFF(fw_reply_t, n_vals),
    OFF(fw_reply_t, next), OFF(fw_reply_t, tail), OFF(fw_reply_t, pending),
    OFF(fw_board_t, hal), OFF(fw_board_t, id), OFF(fw_board_t, can_node), OFF(fw_board_t, cal),
    OFF(fw_board_t, nvm_status), OFF(fw_board_t, nvm_seq), OFF(fw_board_t, streaming), OFF(fw_board_t, seq),
    OFF(fw_board_t, decim), OFF(fw_board_t, phase), OFF(fw_board_t, odr_hz), OFF(fw_board_t, can_cal_have),
    OFF(fw_board_t, can_cal_fields), OFF(fw_board_t, rx_line), OFF(fw_board_t, rx_len),
    OFF(fw_board_t, rx_overflow), OFF(fw_board_t, rx_bad_frames), OFF(fw_board_t, selfcal_on),
    OFF(fw_board_t, selfcal), OFF(fw_board_t, nvm_slot), OFF(fw_board_t, nvm_corrupt_mask),
    OFF(fw_board_t, can_shift), OFF(fw_board_t, can_ug_per_lsb), OFF(fw_board_t, frames_dropped),
    OFF(fw_board_t, boot), OFF(fw_board_t, sensor_reinits), OFF(fw_board_t, selfcal_skew_mg_per_c),
    OFF(fw_board_t, cubic), OFF(fw_board_t, sft_stage), OFF(fw_board_t, sft_have),
    OFF(fw_board_t, nvm_bad_nonfinite), OFF(fw_board_t, prev_t_us), OFF(fw_board_t, gap_us),
    OFF(fw_board_t, gap_lo), OFF(fw_board_t, gap_span), OFF(fw_board_t, src_rate_per_us),
    OFF(fw_board_t, counts_per_g), OFF(fw_board_t, reply),
};

static int same(const char *a, const char *b)
{
    while (*a && *a == *b) { a++; b++; }
    return *a == *b;
}

uint32_t fw_layout(const char *name)
{
    for (uint32_t i = 0; i < (uint32_t)(sizeof LAYOUT / sizeof LAYOUT[0]); i++)
        if (same(LAYOUT[i].name, name)) return LAYOUT[i].value;
    return 0xFFFFFFFFu;
}
