/* fw_bridge.c: sensor bridge line parser (see fw_bridge.h). */
#include <string.h>
#include "fw_bridge.h"
#include "fw_num.h"

static int copy_text(char *dst, uint32_t cap, const fw_field_t *f)
{
    if (f->len == 0 || f->len > cap) return -1;
    for (uint32_t i = 0; i < f->len; i++) if (f->p[i] == ',' || f->p[i] == '$' || f->p[i] == '*' || (uint8_t)f->p[i] < 0x21u || (uint8_t)f->p[i] > 0x7Eu) return -1;
    memcpy(dst, f->p, f->len);
    dst[f->len] = 0;
    return 0;
}

static int finite_f32(const fw_field_t *f, float *out)
{
    return fw_parse_f32(f->p, f->len, out) == 0 && fw_f32_finite(*out) ? 0 : -1;
}

static int int32_field(const fw_field_t *f, int32_t *out)
{
    int64_t v;
    if (fw_parse_i64(f->p, f->len, &v) != 0 || v < INT32_MIN || v > INT32_MAX) return -1;
    *out = (int32_t)v;
    return 0;
}

int fw_bridge_line(const uint8_t *line, uint32_t len, fw_identity_t *id_out, fw_raw_sample_t *s_out)
{
    const uint8_t *body;
    fw_field_t f[FW_MAX_FIELDS];
    int32_t n = fw_unframe(line, len, &body);
    if (n < 0) return FW_BRIDGE_NONE;
    uint32_t nf = fw_split(body, (uint32_t)n, f, FW_MAX_FIELDS);
    if (nf == 7 && fw_field_is(&f[0], "B")) {
        fw_identity_t id;
        memset(&id, 0, sizeof id);
        if (copy_text(id.serial, FW_SERIAL_MAX, &f[1]) || copy_text(id.sensor, FW_SENSOR_MAX, &f[2])
            || finite_f32(&f[3], &id.ug_per_lsb) || finite_f32(&f[4], &id.t_lsb_per_c)
            || finite_f32(&f[5], &id.t_lsb_at_25c) || finite_f32(&f[6], &id.odr_hz)
            || !(id.ug_per_lsb > 0.0f) || !(id.odr_hz > 0.0f) || id.t_lsb_per_c == 0.0f)
            return FW_BRIDGE_NONE;
        memcpy(id.fw, FW_FW_VERSION_DEFAULT, sizeof FW_FW_VERSION_DEFAULT);
        *id_out = id;
        return FW_BRIDGE_IDENTITY;
    }
    if (nf == 6 && fw_field_is(&f[0], "S")) {
        fw_raw_sample_t s;
        int64_t t;
        if (fw_parse_i64(f[1].p, f[1].len, &t) != 0 || t < 0) return FW_BRIDGE_NONE;
        s.t_us = (uint32_t)(uint64_t)t;
        for (int i = 0; i < 3; i++) if (int32_field(&f[2 + i], &s.acc[i])) return FW_BRIDGE_NONE;
        if (int32_field(&f[5], &s.temp)) return FW_BRIDGE_NONE;
        *s_out = s;
        return FW_BRIDGE_SAMPLE;
    }
    return FW_BRIDGE_NONE;
}

int fw_bridge_fault(const uint8_t *line, uint32_t len, fw_bridge_fault_t *out)
{
    const uint8_t *body;
    fw_field_t f[FW_MAX_FIELDS];
    int32_t n = fw_unframe(line, len, &body);
    if (n < 0) return FW_BRIDGE_NONE;
    uint32_t nf = fw_split(body, (uint32_t)n, f, FW_MAX_FIELDS);
    if (nf < 2 || !fw_field_is(&f[0], "X")) return FW_BRIDGE_NONE;
    fw_bridge_fault_t x = { FW_FAULT_NONE, 0.0f };
    if (nf == 2 && fw_field_is(&f[1], "hardfault")) x.kind = FW_FAULT_HARDFAULT;
    else if (nf == 2 && fw_field_is(&f[1], "hang")) x.kind = FW_FAULT_HANG;
    else if (nf == 3 && fw_field_is(&f[1], "selfcal_skew") && finite_f32(&f[2], &x.value) == 0) x.kind = FW_FAULT_SELFCAL_SKEW;
    else return FW_BRIDGE_NONE;
    *out = x;
    return FW_BRIDGE_FAULT;
}

uint32_t fw_bridge_ready(uint8_t *out, uint32_t cap)
{
    return fw_frame((const uint8_t *)"READY", 5, out, cap);
}

uint32_t fw_bridge_boot(uint8_t *out, uint32_t cap)
{
    return fw_frame((const uint8_t *)"BOOT", 4, out, cap);
}

uint32_t fw_bridge_init(uint8_t *out, uint32_t cap)
{
    return fw_frame((const uint8_t *)"INIT", 4, out, cap);
}
