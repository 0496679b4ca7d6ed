/* fw_serial_proto.c: design 3.1 commands (station to board) and frames (board to station), plus
 * the on-board self-calibration frames $SCAL / $SCRR and their G / R replies. */
#include <string.h>
#include "fw_board_internal.h"
#include "fw_nvm.h"
#include "fw_num.h"

#define CORRUPT_TEXT "calibration record corrupt"

static void send_ack(fw_board_t *b, const char *cmd)
{
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, cmd);
    fw_send_tx(b, &t);
}

static void send_identity(fw_board_t *b)
{
    fw_tx_t t;
    fw_tx_begin(&t, "I");
    fw_tx_str(&t, b->id.serial);
    fw_tx_str(&t, b->id.sensor);
    fw_tx_str(&t, b->id.fw);
    fw_tx_f32(&t, b->id.ug_per_lsb);     /* fmt_number: "60", "3.9", "-9.05", "1885", "3.125" */
    fw_tx_f32(&t, b->id.t_lsb_per_c);
    fw_tx_f32(&t, b->id.t_lsb_at_25c);
    fw_tx_f32(&t, b->odr_hz);
    fw_send_tx(b, &t);
}

/* Parse n finite float32 values (-0 stored as +0 like cal_record.to_f32). 0 or -1 (error sent). */
static int parse_values(fw_board_t *b, const char *cmd, const fw_field_t *f, uint32_t nf, uint32_t n, float *out)
{
    if (nf != n + 1u) {
        fw_send_error(b, cmd, n == 6u ? "need 6 values" : "need 12 values", NULL, 0);
        return -1;
    }
    for (uint32_t i = 0; i < n; i++) {
        float v;
        if (fw_parse_real(f[1 + i].p, f[1 + i].len, NULL, &v) != 0) {
            fw_send_error(b, cmd, "bad number ", f[1 + i].p, f[1 + i].len);
            return -1;
        }
        if (!fw_f32_finite(v)) {
            fw_send_error(b, cmd, "non-finite value ", f[1 + i].p, f[1 + i].len);
            return -1;
        }
        out[i] = v + 0.0f;
        if (fw_f32_bits(out[i]) == 0x80000000u) out[i] = 0.0f;
    }
    return 0;
}

static void cmd_calw(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    fw_cal_t c = b->cal;
    if (parse_values(b, "CALW", f, nf, 6, c.thermal) != 0) return;
    c.thermal_crc = fw_crc32_f32(c.thermal, 6);
    if (fw_nvm_store(b, &c) != 0) { fw_send_error(b, "CALW", "flash write failed", NULL, 0); return; }
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, "CALW");
    fw_tx_hex32(&t, b->cal.thermal_crc);
    fw_send_tx(b, &t);
}

static void cmd_sfew(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    fw_cal_t c = b->cal;
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "SFEW", CORRUPT_TEXT, NULL, 0); return; }
    if (parse_values(b, "SFEW", f, nf, 12, c.sfem) != 0) return;
    c.has_sfem = 1;
    c.sfem_crc = fw_crc32_f32(c.sfem, 12);
    if (fw_nvm_store(b, &c) != 0) { fw_send_error(b, "SFEW", "flash write failed", NULL, 0); return; }
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, "SFEW");
    fw_tx_hex32(&t, b->cal.sfem_crc);
    fw_send_tx(b, &t);
}

static void cmd_calr(fw_board_t *b)
{
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "CALR", CORRUPT_TEXT, NULL, 0); return; }
    fw_tx_t t;
    fw_tx_begin(&t, "C");
    for (int i = 0; i < 6; i++) fw_tx_f32(&t, b->cal.thermal[i]);
    fw_tx_hex32(&t, b->cal.thermal_crc);
    fw_tx_str(&t, b->cal.comp ? "1" : "0");
    fw_send_tx(b, &t);
}

static void cmd_sfer(fw_board_t *b)
{
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "SFER", CORRUPT_TEXT, NULL, 0); return; }
    if (!b->cal.has_sfem) { fw_send_error(b, "SFER", "no SFEM stored", NULL, 0); return; }
    fw_tx_t t;
    fw_tx_begin(&t, "S");
    for (int i = 0; i < 12; i++) fw_tx_f32(&t, b->cal.sfem[i]);
    fw_tx_hex32(&t, b->cal.sfem_crc);
    fw_send_tx(b, &t);
}

static int flag_arg(fw_board_t *b, const char *cmd, const fw_field_t *f, uint32_t nf)
{
    if (nf == 2 && (fw_field_is(&f[1], "0") || fw_field_is(&f[1], "1"))) return f[1].p[0] == '1';
    fw_send_error(b, cmd, "need 0 or 1", NULL, 0);
    return -1;
}

static void cmd_comp(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    int on = flag_arg(b, "COMP", f, nf);
    if (on < 0) return;
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "COMP", CORRUPT_TEXT, NULL, 0); return; }
    if (b->cal.comp != (uint8_t)on) {
        fw_cal_t c = b->cal;
        c.comp = (uint8_t)on;
        if (fw_nvm_store(b, &c) != 0) { fw_send_error(b, "COMP", "flash write failed", NULL, 0); return; }
    }
    send_ack(b, "COMP");
}

static void cmd_odr(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    double hz;
    uint32_t k = 0;
    if (nf != 2) { fw_send_error(b, "ODR", "need 1 value", NULL, 0); return; }
    if (fw_parse_real(f[1].p, f[1].len, &hz, NULL) == 0) k = fw_odr_ratio((double)b->id.odr_hz, hz);
    if (k == 0) { fw_send_error(b, "ODR", "unsupported rate ", f[1].p, f[1].len); return; }
    fw_set_decimation(b, k);
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, "ODR");
    fw_tx_raw(&t, ",", 1);
    fw_tx_raw(&t, f[1].p, f[1].len);
    fw_send_tx(b, &t);
}

static void cmd_scrr(fw_board_t *b)
{
    fw_selfcal_result_t r;
    if (b->selfcal.n_seg == 0) { fw_send_error(b, "SCRR", "no result: no segments", NULL, 0); return; }
    if (fw_selfcal_result(&b->selfcal, &r) != 0) {
        fw_send_error(b, "SCRR", "no result: no orientation has two segments far enough apart in temperature",
                      NULL, 0);
        return;
    }
    fw_tx_t t;
    fw_tx_begin(&t, "R");
    for (int i = 0; i < 3; i++) fw_tx_f32(&t, r.tdb_mg_per_c[i]);
    for (int i = 0; i < 3; i++) fw_tx_f32(&t, r.tdsf_ppm_per_c[i]);
    fw_tx_u32(&t, r.n_segments);
    fw_tx_u32(&t, r.flags);
    fw_send_tx(b, &t);
}

void fw_serial_segment(fw_board_t *b, const fw_segment_t *seg)
{
    fw_tx_t t;
    fw_tx_begin(&t, "G");
    fw_tx_u32(&t, seg->index);
    fw_tx_u32(&t, seg->orientation);
    fw_tx_u32(&t, seg->t_end_us);
    for (int i = 0; i < 3; i++) fw_tx_f32(&t, seg->acc_g[i]);
    fw_tx_f32(&t, seg->temp_c);
    fw_tx_u32(&t, seg->n);
    fw_send_tx(b, &t);
}

void fw_serial_sample(fw_board_t *b, const fw_raw_sample_t *s)
{
    int32_t acc[3] = { s->acc[0], s->acc[1], s->acc[2] };
    if (b->cal.comp) fw_compensate(&b->cal, b->id.ug_per_lsb, s->acc, fw_temp_c(&b->id, s->temp), acc);
    fw_tx_t t;
    fw_tx_begin(&t, "D");
    fw_tx_u32(&t, b->seq);
    fw_tx_u32(&t, s->t_us);
    for (int i = 0; i < 3; i++) fw_tx_i32(&t, acc[i]);
    fw_tx_i32(&t, s->temp);
    fw_send_tx(b, &t);
    b->seq++;
}

/* Commands without arguments: 1 when the count is right, else the error is sent. */
static int no_args(fw_board_t *b, const char *cmd, uint32_t nf)
{
    if (nf == 1) return 1;
    fw_send_error(b, cmd, "unexpected arguments", NULL, 0);
    return 0;
}

void fw_serial_command(fw_board_t *b, const uint8_t *body, uint32_t len)
{
    fw_field_t f[FW_MAX_FIELDS];
    uint32_t nf = fw_split(body, len, f, FW_MAX_FIELDS);
    const fw_field_t *c = &f[0];
    if (fw_field_is(c, "ID")) { if (no_args(b, "ID", nf)) send_identity(b); }
    else if (fw_field_is(c, "START")) { if (no_args(b, "START", nf)) { b->streaming = 1; send_ack(b, "START"); } }
    else if (fw_field_is(c, "STOP")) { if (no_args(b, "STOP", nf)) { b->streaming = 0; send_ack(b, "STOP"); } }
    else if (fw_field_is(c, "ODR")) cmd_odr(b, f, nf);
    else if (fw_field_is(c, "CALW")) cmd_calw(b, f, nf);
    else if (fw_field_is(c, "SFEW")) cmd_sfew(b, f, nf);
    else if (fw_field_is(c, "CALR")) { if (no_args(b, "CALR", nf)) cmd_calr(b); }
    else if (fw_field_is(c, "SFER")) { if (no_args(b, "SFER", nf)) cmd_sfer(b); }
    else if (fw_field_is(c, "COMP")) cmd_comp(b, f, nf);
    else if (fw_field_is(c, "SCAL")) {
        int on = flag_arg(b, "SCAL", f, nf);
        if (on < 0) return;
        if (on) fw_selfcal_reset(&b->selfcal);
        b->selfcal_on = (uint8_t)on;
        send_ack(b, "SCAL");
    }
    else if (fw_field_is(c, "SCRR")) { if (no_args(b, "SCRR", nf)) cmd_scrr(b); }
    else b->rx_bad_frames++;   /* unknown type (or empty body): counted, skipped */
}
