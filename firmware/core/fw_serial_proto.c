/* fw_serial_proto.c: design 3.1 commands (station to board) and frames (board to station), plus
 * the on-board self-calibration frames $SCAL / $SCRR and their G / R replies, and the additions of
 * docs/design.md 3.1: identity keys, record keys after CALR, the version-2 record's cubic
 * SFEM ($SFTW staging, $SFTC commit, $SFTR read-back as T frames). */
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

static const char *const REC_STATE_WORDS[] = { "ok", "fallback", "empty", "corrupt" };

/* float32 from decimal text (Python float() syntax, float32(float(text))): 0, or -1 when not a number. */
static int parse_f32(const char *p, uint32_t len, float *out)
{
    return fw_parse_f32(p, len, out);
}

/* ",<key><decimal>" */
static void tx_key_u32(fw_tx_t *t, const char *key, uint32_t v)
{
    char num[12];
    fw_tx_str(t, key);
    fw_tx_raw(t, num, fw_fmt_u32(num, v));
}

/* ",<key><8 hex digits>" */
static void tx_key_hex32(fw_tx_t *t, const char *key, uint32_t v)
{
    char num[9];
    fw_tx_str(t, key);
    fw_tx_raw(t, num, fw_fmt_hex32(num, v));
}

/* The record in force: ",rec_ver=..,rec_gen=..,rec_slot=..,rec_state=.." (identity and C frames). */
static void tx_record_keys(fw_tx_t *t, const fw_board_t *b)
{
    tx_key_u32(t, "rec_ver=", fw_board_rec_version(b));
    tx_key_u32(t, "rec_gen=", b->nvm_slot >= 0 ? b->nvm_seq : 0u);
    if (b->nvm_slot >= 0) tx_key_u32(t, "rec_slot=", (uint32_t)b->nvm_slot);
    else fw_tx_str(t, "rec_slot=-");
    fw_tx_str(t, "rec_state=");
    fw_tx_raw(t, REC_STATE_WORDS[fw_board_rec_state(b)], (uint32_t)strlen(REC_STATE_WORDS[fw_board_rec_state(b)]));
}

/* ---- long replies: recorded by the command, formatted a few numbers per call (fw_board.h) ---- */

/* Record a reply of kind `kind` whose numbers are vals[0..n) (copied) followed by `tail`; the
 * caller may append a prefix to r->tx (e.g. ",<k>") and set r->tail_u32. */
static fw_reply_t *reply_begin(fw_board_t *b, const char *kind, const float *vals, uint32_t n, uint8_t tail)
{
    fw_reply_t *r = &b->reply;
    fw_tx_begin(&r->tx, kind);
    memcpy(r->vals, vals, n * sizeof(float));
    r->n_vals = (uint8_t)n;
    r->next = 0;
    r->tail = tail;
    r->tail_u32[0] = 0;
    r->tail_u32[1] = 0;
    r->pending = 1;
    return r;
}

void fw_reply_step(fw_board_t *b, uint32_t max_values)
{
    fw_reply_t *r = &b->reply;
    if (!r->pending) return;
    uint32_t next = r->next, end = r->n_vals;
    if (max_values < end - next) end = next + max_values;
    for (; next < end; next++) fw_tx_f32(&r->tx, r->vals[next]);
    r->next = (uint8_t)next;
    if (next < r->n_vals) return;
    switch (r->tail) {
    case FW_REPLY_TAIL_HEX:
        fw_tx_hex32(&r->tx, r->tail_u32[0]);
        break;
    case FW_REPLY_TAIL_CALR:
        fw_tx_hex32(&r->tx, r->tail_u32[0]);
        fw_tx_str(&r->tx, r->tail_u32[1] ? "1" : "0");
        tx_record_keys(&r->tx, b);   /* no command ran since it was recorded: the record in force then */
        break;
    case FW_REPLY_TAIL_U32X2:
        fw_tx_u32(&r->tx, r->tail_u32[0]);
        fw_tx_u32(&r->tx, r->tail_u32[1]);
        break;
    default:
        break;
    }
    r->pending = 0;
    fw_send_tx(b, &r->tx);
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
    fw_tx_str(&t, "reset=");
    const char *word = fw_reset_word(b->boot.cause);
    fw_tx_raw(&t, word, (uint32_t)strlen(word));
    tx_key_u32(&t, "boots=", b->boot.boots);
    if (b->boot.cause == FW_RESET_FAULT) {
        tx_key_hex32(&t, "fault=", b->boot.fault_cfsr);
        tx_key_hex32(&t, "fault_pc=", b->boot.fault_pc);
    }
    tx_record_keys(&t, b);
    fw_tx_str(&t, "caps=scal+sfem3");
    tx_key_u32(&t, "sensor_reinit=", b->sensor_reinits);
    fw_send_tx(b, &t);
    fw_rec_state_t st = fw_board_rec_state(b);
    if (st == FW_REC_FALLBACK || st == FW_REC_CORRUPT) fw_send_nvm_errors(b);
}

/* Parse the n fields f[0..n-1] as finite float32 values (-0 stored as +0 like cal_record.to_f32).
 * 0 or -1 (error sent). */
static int parse_floats(fw_board_t *b, const char *cmd, const fw_field_t *f, uint32_t n, float *out)
{
    for (uint32_t i = 0; i < n; i++) {
        float v;
        if (parse_f32(f[i].p, f[i].len, &v) != 0) {
            fw_send_error(b, cmd, "bad number ", f[i].p, f[i].len);
            return -1;
        }
        if (!fw_f32_finite(v)) {
            fw_send_error(b, cmd, "non-finite value ", f[i].p, f[i].len);
            return -1;
        }
        out[i] = v + 0.0f;
        if (fw_f32_bits(out[i]) == 0x80000000u) out[i] = 0.0f;
    }
    return 0;
}

/* CALW / SFEW: exactly n values after the command. 0 or -1 (error sent). */
static int parse_values(fw_board_t *b, const char *cmd, const fw_field_t *f, uint32_t nf, uint32_t n, float *out)
{
    if (nf != n + 1u) {
        fw_send_error(b, cmd, n == 6u ? "need 6 values" : "need 12 values", NULL, 0);
        return -1;
    }
    return parse_floats(b, cmd, f + 1, n, out);
}

/* 8 hex digits (either case) as written by fmt_crc. 0 or -1. */
static int parse_hex32(const fw_field_t *f, uint32_t *out)
{
    uint32_t v = 0;
    if (f->len != 8u) return -1;
    for (uint32_t i = 0; i < 8u; i++) {
        char c = f->p[i];
        uint32_t d;
        if (c >= '0' && c <= '9') d = (uint32_t)(c - '0');
        else if (c >= 'A' && c <= 'F') d = (uint32_t)(c - 'A') + 10u;
        else if (c >= 'a' && c <= 'f') d = (uint32_t)(c - 'a') + 10u;
        else return -1;
        v = (v << 4) | d;
    }
    *out = v;
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
    fw_reply_t *r = reply_begin(b, "C", b->cal.thermal, 6, FW_REPLY_TAIL_CALR);
    r->tail_u32[0] = b->cal.thermal_crc;
    r->tail_u32[1] = b->cal.comp;
}

static void cmd_sfer(fw_board_t *b)
{
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "SFER", CORRUPT_TEXT, NULL, 0); return; }
    if (!b->cal.has_sfem) { fw_send_error(b, "SFER", "no SFEM stored", NULL, 0); return; }
    reply_begin(b, "S", b->cal.sfem, 12, FW_REPLY_TAIL_HEX)->tail_u32[0] = b->cal.sfem_crc;
}

/* $SFTW,<k>,<12 values>: stage the coefficients of power k (nothing stored until $SFTC). */
static void cmd_sftw(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    float v[12];
    if (nf != 14u) { fw_send_error(b, "SFTW", "need a power and 12 values", NULL, 0); return; }
    if (f[1].len != 1u || f[1].p[0] < '0' || f[1].p[0] > '3') {
        fw_send_error(b, "SFTW", "bad power ", f[1].p, f[1].len);
        return;
    }
    if (parse_floats(b, "SFTW", f + 2, 12, v) != 0) return;
    uint32_t k = (uint32_t)(f[1].p[0] - '0');
    memcpy(b->sft_stage[k], v, sizeof v);
    b->sft_have |= (uint8_t)(1u << k);
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, "SFTW");
    fw_tx_raw(&t, ",", 1);
    fw_tx_raw(&t, f[1].p, 1);
    fw_send_tx(b, &t);
}

/* $SFTC,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>: store a version-2 record (the thermal coefficients, the
 * constant SFEM and compensation switch kept) if all four powers were staged since the last $SFTC,
 * every value is finite, t_lo_c < t_hi_c and the CRC of the 51 values matches. Every $SFTC ends
 * the staging, stored or not. */
static void cmd_sftc(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    const uint8_t have = b->sft_have;
    float head[3];
    uint32_t want;
    fw_cubic_t cu;
    b->sft_have = 0;
    if (nf != 5u) { fw_send_error(b, "SFTC", "need 3 values and a crc", NULL, 0); return; }
    if (parse_floats(b, "SFTC", f + 1, 3, head) != 0) return;
    if (parse_hex32(&f[4], &want) != 0) { fw_send_error(b, "SFTC", "bad crc ", f[4].p, f[4].len); return; }
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "SFTC", CORRUPT_TEXT, NULL, 0); return; }
    if (have != 0x0Fu) { fw_send_error(b, "SFTC", "not all 4 powers staged", NULL, 0); return; }
    if (!(head[1] < head[2])) { fw_send_error(b, "SFTC", "t_lo_c not below t_hi_c", NULL, 0); return; }
    memset(&cu, 0, sizeof cu);
    cu.t_ref_c = head[0];
    cu.t_lo_c = head[1];
    cu.t_hi_c = head[2];
    memcpy(cu.c, b->sft_stage, sizeof cu.c);
    cu.crc = fw_cubic_crc(&cu);
    cu.present = 1;
    if (cu.crc != want) {
        char num[9];
        fw_send_error(b, "SFTC", "crc mismatch: board computed ", num, fw_fmt_hex32(num, cu.crc));
        return;
    }
    if (fw_nvm_store_rec(b, &b->cal, &cu) != 0) { fw_send_error(b, "SFTC", "flash write failed", NULL, 0); return; }
    fw_tx_t t;
    fw_tx_begin(&t, "A");
    fw_tx_str(&t, "SFTC");
    fw_tx_hex32(&t, b->cubic.crc);
    fw_send_tx(b, &t);
}

/* $SFTR,H -> T,H,<t_ref_c>,<t_lo_c>,<t_hi_c>,<crc>; $SFTR,<k> -> T,<k>,<12 values>. */
static void cmd_sftr(fw_board_t *b, const fw_field_t *f, uint32_t nf)
{
    if (nf != 2u || f[1].len != 1u || !(f[1].p[0] == 'H' || (f[1].p[0] >= '0' && f[1].p[0] <= '3'))) {
        fw_send_error(b, "SFTR", "need H or a power 0..3", NULL, 0);
        return;
    }
    if (b->nvm_status == FW_NVM_CORRUPT) { fw_send_error(b, "SFTR", CORRUPT_TEXT, NULL, 0); return; }
    if (!b->cubic.present) { fw_send_error(b, "SFTR", "no cubic SFEM stored", NULL, 0); return; }
    fw_reply_t *r;
    if (f[1].p[0] == 'H') {
        const float head[3] = { b->cubic.t_ref_c, b->cubic.t_lo_c, b->cubic.t_hi_c };
        r = reply_begin(b, "T", head, 3, FW_REPLY_TAIL_HEX);
        r->tail_u32[0] = b->cubic.crc;
    } else {
        r = reply_begin(b, "T", b->cubic.c[f[1].p[0] - '0'], 12, FW_REPLY_TAIL_NONE);
    }
    fw_tx_raw(&r->tx, ",", 1);
    fw_tx_raw(&r->tx, f[1].p, 1);
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
    float hz;
    uint32_t k = 0;
    if (nf != 2) { fw_send_error(b, "ODR", "need 1 value", NULL, 0); return; }
    if (parse_f32(f[1].p, f[1].len, &hz) == 0) k = fw_rate_ratio(b->id.odr_hz, hz);
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
    float v[6];
    /* simulation fault (bridge $X,selfcal_skew): a calibrator whose TDB disagrees by this much */
    for (int i = 0; i < 3; i++) v[i] = r.tdb_mg_per_c[i] + b->selfcal_skew_mg_per_c;
    for (int i = 0; i < 3; i++) v[3 + i] = r.tdsf_ppm_per_c[i];
    fw_reply_t *p = reply_begin(b, "R", v, 6, FW_REPLY_TAIL_U32X2);
    p->tail_u32[0] = r.n_segments;
    p->tail_u32[1] = r.flags;
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
    if (b->cal.comp) fw_apply_comp(b, s, fw_temp_c(&b->id, s->temp), acc);
    fw_tx_t t;
    fw_tx_begin(&t, "D");
    fw_tx_u32(&t, b->seq);
    fw_tx_u32(&t, s->t_us);
    for (int i = 0; i < 3; i++) fw_tx_i32(&t, acc[i]);
    fw_tx_i32(&t, s->temp);
    fw_send_tx(b, &t);
    b->seq++;   /* a sample that could not be framed or sent still counts (contract v2) */
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
    /* a reply still pending goes out first: replies keep the order of their commands */
    if (b->reply.pending) fw_reply_step(b, FW_REPLY_VALUES_MAX);
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
    else if (fw_field_is(c, "SFTW")) cmd_sftw(b, f, nf);
    else if (fw_field_is(c, "SFTC")) cmd_sftc(b, f, nf);
    else if (fw_field_is(c, "SFTR")) cmd_sftr(b, f, nf);
    else b->rx_bad_frames++;   /* unknown type (or empty body): counted, skipped */
}
