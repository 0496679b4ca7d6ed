/* fuzz_common.c: RAM HAL, invariant checks and input decoders shared by the fuzz targets. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "fuzz_common.h"
#include "fw_frame.h"
#include "fw_num.h"

/* ---------------------------------------------------------------------------------------------
 * The coefficients a board applies: every float field of fw_cal_t (version 1: thermal, SFEM) and of
 * fw_cubic_t (version 2: the cubic SFEM, b->cubic). Listed by hand because C cannot enumerate a
 * struct: when either struct changes size (a new coefficient array), this stops compiling until the
 * new float fields are added here and the size below is updated (x86_64 layout).
 * ------------------------------------------------------------------------------------------- */
#define FZ_CAL_BYTES 84u
#define FZ_CUBIC_BYTES 212u
typedef char fw_cal_t_changed_so_list_its_float_fields_in_fz_cal_floats[(sizeof(fw_cal_t) == FZ_CAL_BYTES) ? 1 : -1];
typedef char fw_cubic_t_changed_so_list_its_float_fields_in_fz_cubic_floats[(sizeof(fw_cubic_t) == FZ_CUBIC_BYTES) ? 1 : -1];

#define FZ_FIELD(type, f) { #f, offsetof(type, f), (uint32_t)(sizeof(((type *)0)->f) / sizeof(float)) }
const fz_float_field_t fz_cal_floats[] = {
    FZ_FIELD(fw_cal_t, thermal),
    FZ_FIELD(fw_cal_t, sfem),
};
const uint32_t fz_cal_n_fields = (uint32_t)(sizeof fz_cal_floats / sizeof fz_cal_floats[0]);
const fz_float_field_t fz_cubic_floats[] = {
    FZ_FIELD(fw_cubic_t, t_ref_c),
    FZ_FIELD(fw_cubic_t, t_lo_c),
    FZ_FIELD(fw_cubic_t, t_hi_c),
    FZ_FIELD(fw_cubic_t, c),
};
const uint32_t fz_cubic_n_fields = (uint32_t)(sizeof fz_cubic_floats / sizeof fz_cubic_floats[0]);

/* --- independent codecs ---------------------------------------------------------------------- */

uint32_t fz_crc32(const uint8_t *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        c ^= p[i];
        for (int k = 0; k < 8; k++) c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
    }
    return ~c;
}

uint32_t fz_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

void fz_put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}

static int f32_finite(float v)
{
    uint32_t u;
    memcpy(&u, &v, sizeof u);
    return (u & 0x7F800000u) != 0x7F800000u;
}

void fz_fix_record_crcs(uint8_t img[FW_NVM_SLOT_BYTES])
{
    uint32_t version = (uint32_t)img[4] | ((uint32_t)img[5] << 8);
    uint32_t len = (uint32_t)img[6] | ((uint32_t)img[7] << 8);
    if ((version == 1u && len == 104u) || (version == 2u && len == 312u)) {
        fz_put_u32(img + 36, fz_crc32(img + 12, 24));
        if (img[40] == 1u) fz_put_u32(img + 44 + 48, fz_crc32(img + 44, 48));
        else fz_put_u32(img + 92, 0);
    }
    if (version == 2u && len == 312u) fz_put_u32(img + 304, fz_crc32(img + 100, 204));   /* the 51 cubic values */
    if (len >= 8u && len <= FW_NVM_SLOT_BYTES) fz_put_u32(img + len - 4u, fz_crc32(img, len - 4u));
}

/* --- invariants ------------------------------------------------------------------------------ */

static uint32_t nonfinite(const void *obj, const fz_float_field_t *fields, uint32_t n_fields, const char *prefix,
                          char *where, size_t where_cap)
{
    uint32_t bad = 0;
    const uint8_t *base = obj;
    for (uint32_t f = 0; f < n_fields; f++) {
        for (uint32_t i = 0; i < fields[f].count; i++) {
            float v;
            memcpy(&v, base + fields[f].offset + i * sizeof(float), sizeof v);
            if (f32_finite(v)) continue;
            if (bad == 0 && where && where_cap)
                snprintf(where, where_cap, "%s%s[%u] = %g", prefix, fields[f].name, (unsigned)i, (double)v);
            bad++;
        }
    }
    return bad;
}

uint32_t fz_cal_nonfinite(const fw_cal_t *c, char *where, size_t where_cap)
{
    return nonfinite(c, fz_cal_floats, fz_cal_n_fields, "", where, where_cap);
}

uint32_t fz_cubic_nonfinite(const fw_cubic_t *c, char *where, size_t where_cap)
{
    return nonfinite(c, fz_cubic_floats, fz_cubic_n_fields, "cubic.", where, where_cap);
}

int fz_written_image_ok(const uint8_t img[FW_NVM_SLOT_BYTES], char *why, size_t why_cap)
{
    fw_cal_t c;
    fw_cubic_t cu;
    uint32_t gen = 0;
    char where[96];
    fw_slot_state_t st = fw_nvm_decode_rec(img, FW_NVM_SLOT_BYTES, &c, &cu, &gen);
    if (st != FW_SLOT_VALID) {
        snprintf(why, why_cap, "fw_nvm_decode_rec says %s for the image just written",
                 st == FW_SLOT_ERASED ? "ERASED" : st == FW_SLOT_NONFINITE ? "NONFINITE" : "CORRUPT");
        return -1;
    }
    if (fz_cal_nonfinite(&c, where, sizeof where) || fz_cubic_nonfinite(&cu, where, sizeof where)) {
        snprintf(why, why_cap, "the record written holds a non-finite coefficient: %s", where);
        return -1;
    }
    return 0;
}

int fz_serial_frame_ok(const uint8_t *out, uint32_t len)
{
    const uint8_t *body;
    if (len < 5u || out[0] != '$' || out[len - 1u] != '\n') return -1;
    for (uint32_t i = 0; i + 1u < len; i++) if (out[i] == '\n' || (i > 0 && out[i] == '$')) return -1;
    return fw_unframe(out, len - 1u, &body) < 0 ? -1 : 0;
}

void fz_violation(const char *what, const char *detail, const char *after)
{
    fprintf(stderr, "FW_FUZZ INVARIANT VIOLATION: %s: %s (after %s)\n", what, detail, after);
    fflush(stderr);
    abort();
}

void fz_check_board(const fz_rig_t *rig, const char *after)
{
    char where[96];
    if (fz_cal_nonfinite(&rig->board.cal, where, sizeof where) || fz_cubic_nonfinite(&rig->board.cubic, where, sizeof where))
        fz_violation("non-finite coefficient applied", where, after);
}

/* --- RAM HAL ---------------------------------------------------------------------------------- */

static int ram_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    fz_rig_t *rig = ctx;
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) return -1;
    memcpy(buf, rig->nvm.slot[slot], len);
    return 0;
}

static int ram_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    fz_rig_t *rig = ctx;
    fz_nvm_t *n = &rig->nvm;
    uint8_t img[FW_NVM_SLOT_BYTES];
    char why[160];
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) fz_violation("NVM write outside a slot", "slot/len", "nvm_write");
    memset(img, 0xFF, sizeof img);   /* erase, then program len bytes */
    memcpy(img, buf, len);
    if (fz_written_image_ok(img, why, sizeof why) != 0) fz_violation("NVM write not valid", why, "nvm_write");
    uint8_t fault = n->writes < sizeof n->fault_plan ? n->fault_plan[n->writes] : FZ_FLASH_OK;
    uint32_t prefix = (n->writes * 37u + 11u) % (len ? len : 1u);
    n->writes++;
    switch (fault % 5u) {
    case FZ_FLASH_FAIL: return -1;
    case FZ_FLASH_TORN_FAIL:
    case FZ_FLASH_TORN_OK:
        memset(n->slot[slot], 0xFF, FW_NVM_SLOT_BYTES);
        memcpy(n->slot[slot], img, prefix);
        return fault % 5u == FZ_FLASH_TORN_FAIL ? -1 : 0;
    case FZ_FLASH_FLIP:
        memcpy(n->slot[slot], img, FW_NVM_SLOT_BYTES);
        n->slot[slot][prefix] ^= 0x10u;
        return 0;
    default:
        memcpy(n->slot[slot], img, FW_NVM_SLOT_BYTES);
        return 0;
    }
}

static void uart_sink(void *ctx, const uint8_t *buf, uint32_t len)
{
    fz_rig_t *rig = ctx;
    rig->frames_out++;
    if (fz_serial_frame_ok(buf, len) != 0) {
        char detail[96];
        snprintf(detail, sizeof detail, "%u bytes starting %.40s", (unsigned)len, (const char *)buf);
        for (char *p = detail; *p; p++) if ((unsigned char)*p < 0x20u) *p = '?';
        fz_violation("serial frame malformed", detail, "uart_write");
    }
}

static void can_sink(void *ctx, uint16_t id, uint8_t dlc, const uint8_t *data)
{
    fz_rig_t *rig = ctx;
    (void)data;
    rig->frames_out++;
    if (dlc > 8u) fz_violation("CAN frame too long", "dlc > 8", "can_send");
    if (id != 0x180u + rig->can_node && id != 0x580u + rig->can_node)
        fz_violation("CAN frame on a foreign identifier", "id not 0x180+N or 0x580+N", "can_send");
}

/* --- presets ---------------------------------------------------------------------------------- */

void fz_identity(uint32_t index, fw_identity_t *id)
{
    memset(id, 0, sizeof *id);
    if (index & 1u) {
        memcpy(id->serial, "SIM0002", 8);
        memcpy(id->sensor, "ADXL355", 8);
        id->ug_per_lsb = 3.9f;
        id->t_lsb_per_c = -9.05f;
        id->t_lsb_at_25c = 1885.0f;
        id->odr_hz = 3.125f;
    } else {
        memcpy(id->serial, "F4000102030405060708090A0B", 27);
        memcpy(id->sensor, "LIS3DSH", 8);
        id->ug_per_lsb = 60.0f;
        id->t_lsb_per_c = 1.0f;
        id->t_lsb_at_25c = 0.0f;
        id->odr_hz = 100.0f;
    }
    memcpy(id->fw, "fw-c-fuzz", 10);
}

void fz_nvm_preset(fz_nvm_t *n, uint32_t index)
{
    static const float THERMAL[6] = { 0.5f, -0.25f, 1.125f, -120.0f, 35.5f, -290.0f };
    static const float SFEM[12] = { 1.001f, 0.002f, -0.001f, 0.0005f, 0.998f, 0.003f,
                                    -0.002f, 0.001f, 1.0004f, 0.012f, -0.008f, 0.020f };
    fw_cal_t c;
    uint8_t rec[FW_NVM_RECORD_MAX];
    memset(n, 0, sizeof *n);
    memset(n->slot, 0xFF, sizeof n->slot);
    index &= 3u;
    if (index == 0u) return;
    fw_cal_zero(&c);
    memcpy(c.thermal, THERMAL, sizeof THERMAL);
    c.thermal_crc = fw_crc32_f32(c.thermal, 6);
    c.comp = 1;
    if (index == 2u) {
        memcpy(c.sfem, SFEM, sizeof SFEM);
        c.has_sfem = 1;
        c.sfem_crc = fw_crc32_f32(c.sfem, 12);
    }
    fw_cubic_t cu;
    memset(&cu, 0, sizeof cu);
    if (index == 2u) {   /* version 2: the cubic SFEM too (a gentle one: identity plus small terms) */
        cu.t_ref_c = 25.0f;
        cu.t_lo_c = -10.0f;
        cu.t_hi_c = 60.0f;
        memcpy(cu.c[0], SFEM, sizeof SFEM);
        cu.c[1][0] = 1e-5f;
        cu.c[1][9] = 2e-4f;
        cu.c[2][4] = -1e-7f;
        cu.c[3][8] = 1e-9f;
        cu.crc = fw_cubic_crc(&cu);
        cu.present = 1;
    }
    uint32_t len = fw_nvm_encode_rec(&c, &cu, 7, rec);
    memcpy(n->slot[0], rec, len);
    if (index == 3u) {   /* slot 1: a newer record torn after 60 bytes */
        fw_nvm_encode_rec(&c, &cu, 8, rec);
        memcpy(n->slot[1], rec, 60);
    }
}

/* --- board rig -------------------------------------------------------------------------------- */

void fz_boot(fz_rig_t *rig, const fw_identity_t *id, uint8_t can_node, uint8_t cause)
{
    fw_boot_info_t boot;
    memset(&boot, 0, sizeof boot);
    boot.cause = (uint8_t)(cause % 8u);
    boot.boots = 1u + cause;
    boot.fault_cfsr = cause & 4u ? 0x00010000u : 0u;
    boot.fault_pc = 0x08001234u;
    rig->can_node = can_node;
    memset(&rig->hal, 0, sizeof rig->hal);
    rig->hal.ctx = rig;
    if (can_node) rig->hal.can_send = can_sink;
    else rig->hal.uart_write = uart_sink;
    rig->hal.nvm_read = ram_read;
    rig->hal.nvm_write = ram_write;
    fw_board_init(&rig->board, &rig->hal, id, can_node);
    fw_board_set_boot(&rig->board, &boot);
    fz_check_board(rig, "fw_board_init");
}

void fz_reboot(fz_rig_t *rig)
{
    fw_identity_t id = rig->board.id;
    fw_board_init(&rig->board, &rig->hal, &id, rig->can_node);
    fz_check_board(rig, "power cycle (fw_board_init from the NVM written)");
}

void fz_fix_line_checksum(uint8_t *line, size_t len)
{
    static const char HEX[] = "0123456789ABCDEF";
    size_t star = len, dollar;
    while (star > 0 && line[star - 1] != '*') star--;
    if (star == 0) return;
    star--;                                   /* index of the last '*' */
    if (star + 2u >= len) return;             /* no room for HH */
    for (dollar = star; dollar > 0 && line[dollar - 1] != '$'; dollar--) {}
    if (dollar == 0) return;                  /* no '$' before it: the body starts at dollar */
    uint8_t x = 0;
    for (size_t i = dollar; i < star; i++) x ^= line[i];
    line[star + 1] = (uint8_t)HEX[x >> 4];
    line[star + 2] = (uint8_t)HEX[x & 15u];
}

size_t fz_rewrite_sftc(const fw_board_t *b, const uint8_t *line, size_t len, uint8_t *out, size_t cap)
{
    static const char HEX[] = "0123456789ABCDEF";
    size_t n = len < cap ? len : cap;
    memcpy(out, line, n);
    size_t dollar = len, star = len, comma = len;
    while (dollar > 0 && line[dollar - 1] != '$') dollar--;
    while (star > dollar && line[star - 1] != '*') star--;
    if (dollar == 0 || star <= dollar || star - dollar < 6u || memcmp(line + dollar, "SFTC,", 5) != 0) return n;
    star--;   /* index of the '*' */
    for (comma = star; comma > dollar && line[comma - 1] != ','; comma--) {}
    /* fields 1..3: the three temperatures, as the board parses them (-0 stored as +0) */
    fw_field_t f[FW_MAX_FIELDS];
    if (fw_split(line + dollar, (uint32_t)(star - dollar), f, FW_MAX_FIELDS) != 5u) return n;
    uint8_t le[FW_CUBIC_VALUES * 4u];
    for (uint32_t i = 0; i < 3u; i++) {
        float v;
        uint32_t u;
        if (fw_parse_f32(f[1 + i].p, f[1 + i].len, &v) != 0) return n;
        memcpy(&u, &v, sizeof u);
        if (u == 0x80000000u) u = 0;
        fz_put_u32(le + 4u * i, u);
    }
    for (uint32_t k = 0; k < FW_CUBIC_POWERS; k++) {
        for (uint32_t i = 0; i < 12u; i++) {
            uint32_t u;
            memcpy(&u, &b->sft_stage[k][i], sizeof u);
            fz_put_u32(le + 12u + 48u * k + 4u * i, u);
        }
    }
    uint32_t crc = fz_crc32(le, sizeof le);
    size_t m = comma;   /* keep "$SFTC,a,b,c," then the CRC, then "*" and what followed */
    if (m + 8u + (len - star) > cap) return n;
    memcpy(out, line, m);
    for (int d = 7; d >= 0; d--) out[m++] = (uint8_t)HEX[(crc >> (4 * d)) & 15u];
    memcpy(out + m, line + star, len - star);
    return m + (len - star);
}

void fz_command(fz_rig_t *rig, const char *body)
{
    uint8_t buf[FW_RX_LINE_MAX + 8u];
    size_t n = strlen(body);
    if (n + 5u > sizeof buf) return;
    buf[0] = '$';
    memcpy(buf + 1, body, n);
    buf[n + 1] = '*';
    buf[n + 2] = '0';
    buf[n + 3] = '0';
    fz_fix_line_checksum(buf, n + 4u);
    buf[n + 4] = '\n';
    fw_uart_rx(&rig->board, buf, (uint32_t)(n + 5u));
    fz_check_board(rig, body);
    fw_board_idle(&rig->board);   /* as a target's idle loop: a long reply goes out now */
    fz_check_board(rig, body);
}

void fz_sample(fz_rig_t *rig, int32_t ax, int32_t ay, int32_t az, int32_t temp)
{
    fw_raw_sample_t s;
    float hz = rig->board.id.odr_hz > 0.5f ? rig->board.id.odr_hz : 0.5f;
    if (rig->samples >= FZ_SAMPLE_BUDGET) return;
    rig->samples++;
    s.t_us = rig->clock_us;
    s.acc[0] = ax;
    s.acc[1] = ay;
    s.acc[2] = az;
    s.temp = temp;
    rig->clock_us += hz < 1e6f ? (uint32_t)(1e6f / hz) : 1u;
    fw_sample(&rig->board, &s);
}

static int32_t get_i32(const uint8_t *p) { return (int32_t)fz_get_u32(p); }
static int32_t get_i16(const uint8_t *p) { return (int32_t)(int16_t)(uint16_t)((uint32_t)p[0] | ((uint32_t)p[1] << 8)); }

/* reps+1 samples from one record; the temperature steps every 16 samples (self-calibration needs
 * 1500 stable samples per segment and 20 C between segments to get anywhere). */
static void sample_record(fz_rig_t *rig, uint8_t reps, int8_t temp_step, int32_t ax, int32_t ay, int32_t az, int32_t temp,
                          const char *after)
{
    uint32_t n = (uint32_t)reps * 8u + 1u;
    for (uint32_t k = 0; k < n && rig->samples < FZ_SAMPLE_BUDGET; k++) {
        int64_t t = (int64_t)temp + (int64_t)temp_step * (int64_t)(k / 16u);
        if (t > INT32_MAX) t = INT32_MAX;
        if (t < INT32_MIN) t = INT32_MIN;
        fz_sample(rig, ax, ay, az, (int32_t)t);
    }
    fz_check_board(rig, after);
}

void fz_run_serial_stream(fz_rig_t *rig, const uint8_t *data, size_t size, int fix_checksums)
{
    uint8_t chunk[4096];
    size_t i = 0;
    while (i < size) {
        if (data[i] == 0x00u) {
            if (size - i < 1u + FZ_SAMPLE_RECORD) return;
            const uint8_t *r = data + i + 1;
            sample_record(rig, r[0], (int8_t)r[1], get_i32(r + 2), get_i32(r + 6), get_i32(r + 10), get_i32(r + 14),
                          "sample record");
            i += 1u + FZ_SAMPLE_RECORD;
            continue;
        }
        if (data[i] == 0x01u) {
            if (size - i < 3u) return;
            fw_board_sensor_reinit(&rig->board, (uint32_t)data[i + 1] | ((uint32_t)data[i + 2] << 8));
            fz_check_board(rig, "fw_board_sensor_reinit");
            i += 3u;
            continue;
        }
        size_t j = i;
        while (j < size && data[j] > 0x01u && j - i < sizeof chunk) j++;
        size_t n = j - i;
        memcpy(chunk, data + i, n);
        if (fix_checksums) {   /* line by line: a $SFTC's CRC depends on the $SFTW lines before it */
            size_t start = 0;
            for (size_t k = 0; k < n; k++) {
                if (chunk[k] != '\n') continue;
                uint8_t line[FW_RX_LINE_MAX + 16u];
                size_t end = k > start && chunk[k - 1] == '\r' ? k - 1 : k;
                size_t m = fz_rewrite_sftc(&rig->board, chunk + start, end - start, line, sizeof line - 2u);
                fz_fix_line_checksum(line, m);
                memcpy(line + m, chunk + end, k + 1u - end);   /* the "\r\n" or "\n" */
                fw_uart_rx(&rig->board, line, (uint32_t)(m + k + 1u - end));
                fz_check_board(rig, "fw_uart_rx");
                start = k + 1;
            }
            fw_uart_rx(&rig->board, chunk + start, (uint32_t)(n - start));
        } else {
            fw_uart_rx(&rig->board, chunk, (uint32_t)n);
        }
        fz_check_board(rig, "fw_uart_rx");
        fz_sample(rig, 1000, -2000, 16000, 40);   /* steps a long reply recorded by the run */
        fz_check_board(rig, "fw_sample");
        fw_board_idle(&rig->board);                /* and the idle loop finishes it */
        fz_check_board(rig, "fw_board_idle");
        if (rig->board.reply.pending) fz_violation("reply still pending", "after fw_board_idle", "fw_board_idle");
        i = j;
    }
}

void fz_run_can_stream(fz_rig_t *rig, const uint8_t *data, size_t size)
{
    for (size_t i = 0; i + FZ_CAN_RECORD <= size; i += FZ_CAN_RECORD) {
        const uint8_t *r = data + i;
        if (r[0] & 1u) {
            sample_record(rig, r[3], (int8_t)r[2], get_i16(r + 4), get_i16(r + 6), get_i16(r + 8), get_i16(r + 10),
                          "CAN sample record");
            continue;
        }
        uint16_t id = r[0] & 2u ? (uint16_t)(((uint32_t)r[1] | ((uint32_t)r[2] << 8)) & 0x7FFu)
                                : (uint16_t)(0x600u + rig->can_node);
        uint8_t d[8];
        memcpy(d, r + 4, sizeof d);
        if ((r[0] & 4u) && d[0] == 0x06u) {   /* CAL_COMMIT: the CRC of the fields staged so far */
            uint8_t le[24];
            for (uint32_t k = 0; k < 6u; k++) {
                uint32_t u;
                memcpy(&u, &rig->board.can_cal_fields[k], sizeof u);
                fz_put_u32(le + 4u * k, u);
            }
            fz_put_u32(d + 1, fz_crc32(le, sizeof le));
        }
        fw_can_rx(&rig->board, id, r[3], d);
        fz_check_board(rig, "fw_can_rx");
        fz_sample(rig, 1000, -2000, 16000, 40);
        fz_check_board(rig, "fw_sample");
    }
}

#ifdef FW_FUZZ_SELFTEST
/* The deliberately broken build (linked with -Wl,--wrap=fw_f32_finite): every caller of
 * fw_f32_finite outside fw_num.c (the command parsers' finiteness checks) is told "finite", so a
 * NaN sent in a command reaches the calibration. The harness must catch it (tests/test_firmware_fuzz.py). */
int __wrap_fw_f32_finite(float v);
int __wrap_fw_f32_finite(float v)
{
    (void)v;
    return 1;
}
#endif
