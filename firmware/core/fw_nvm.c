/* fw_nvm.c: calibration record layout (versions 1 and 2), A/B slots, boot selection (layout in fw_nvm.h). */
#include <string.h>
#include "fw_nvm.h"
#include "fw_num.h"

static void put_u16(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}

static uint32_t get_u16(const uint8_t *p) { return (uint32_t)p[0] | ((uint32_t)p[1] << 8); }

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void put_f32s(uint8_t *p, const float *v, uint32_t n)
{
    for (uint32_t i = 0; i < n; i++) put_u32(p + 4 * i, fw_f32_bits(v[i]));
}

/* Reads n float32; returns 1 when every one is finite. */
static int get_f32s(const uint8_t *p, float *v, uint32_t n)
{
    int finite = 1;
    for (uint32_t i = 0; i < n; i++) {
        v[i] = fw_bits_f32(get_u32(p + 4 * i));
        finite &= fw_f32_finite(v[i]);
    }
    return finite;
}

void fw_cal_zero(fw_cal_t *cal)
{
    memset(cal, 0, sizeof *cal);
    cal->thermal_crc = fw_crc32_f32(cal->thermal, 6);
}

uint32_t fw_nvm_encode_rec(const fw_cal_t *cal, const fw_cubic_t *cubic, uint32_t generation,
                           uint8_t *out)
{
    const int v2 = cubic != NULL && cubic->present;
    const uint32_t len = v2 ? FW_NVM_RECORD2_BYTES : FW_NVM_RECORD_BYTES;
    memset(out, 0, len);
    put_u32(out, FW_NVM_MAGIC);
    put_u16(out + 4, v2 ? FW_NVM_VERSION2 : FW_NVM_VERSION);
    put_u16(out + 6, len);
    put_u32(out + 8, generation);
    put_f32s(out + 12, cal->thermal, 6);
    put_u32(out + 36, cal->thermal_crc);
    out[40] = cal->has_sfem ? 1 : 0;
    if (cal->has_sfem) {
        put_f32s(out + 44, cal->sfem, 12);
        put_u32(out + 92, cal->sfem_crc);
    }
    out[96] = cal->comp ? 1 : 0;
    if (v2) {
        const float head[3] = { cubic->t_ref_c, cubic->t_lo_c, cubic->t_hi_c };
        put_f32s(out + 100, head, 3);
        for (uint32_t k = 0; k < FW_CUBIC_POWERS; k++) put_f32s(out + 112 + 48 * k, cubic->c[k], 12);
        put_u32(out + 304, cubic->crc);
    }
    put_u32(out + len - 4u, fw_crc32(0, out, len - 4u));
    return len;
}

void fw_nvm_encode(const fw_cal_t *cal, uint32_t generation, uint8_t out[FW_NVM_RECORD_BYTES])
{
    (void)fw_nvm_encode_rec(cal, NULL, generation, out);
}

fw_slot_state_t fw_nvm_decode(const uint8_t *slot, uint32_t len, fw_cal_t *cal, uint32_t *generation)
{
    return fw_nvm_decode_rec(slot, len, cal, NULL, generation);
}

fw_slot_state_t fw_nvm_decode_rec(const uint8_t *slot, uint32_t len, fw_cal_t *cal, fw_cubic_t *cubic,
                                  uint32_t *generation)
{
    uint32_t i;
    for (i = 0; i < len && slot[i] == 0xFFu; i++) {}
    if (i == len) return FW_SLOT_ERASED;
    if (len < FW_NVM_RECORD_BYTES || get_u32(slot) != FW_NVM_MAGIC) return FW_SLOT_CORRUPT;
    const uint32_t version = get_u16(slot + 4), rec_len = get_u16(slot + 6);
    if (!((version == FW_NVM_VERSION && rec_len == FW_NVM_RECORD_BYTES)
          || (version == FW_NVM_VERSION2 && rec_len == FW_NVM_RECORD2_BYTES)) || rec_len > len)
        return FW_SLOT_CORRUPT;
    if (get_u32(slot + rec_len - 4u) != fw_crc32(0, slot, rec_len - 4u) || slot[40] > 1 || slot[96] > 1)
        return FW_SLOT_CORRUPT;
    fw_cal_t c;
    fw_cubic_t cu;
    int finite;
    memset(&c, 0, sizeof c);
    memset(&cu, 0, sizeof cu);
    finite = get_f32s(slot + 12, c.thermal, 6);
    c.thermal_crc = get_u32(slot + 36);
    c.has_sfem = slot[40];
    if (c.has_sfem) finite &= get_f32s(slot + 44, c.sfem, 12);
    c.sfem_crc = get_u32(slot + 92);
    c.comp = slot[96];
    if (c.thermal_crc != fw_crc32_f32(c.thermal, 6)) return FW_SLOT_CORRUPT;
    if (c.has_sfem ? c.sfem_crc != fw_crc32_f32(c.sfem, 12) : c.sfem_crc != 0) return FW_SLOT_CORRUPT;
    if (version == FW_NVM_VERSION2) {
        float head[3];
        finite &= get_f32s(slot + 100, head, 3);
        cu.t_ref_c = head[0];
        cu.t_lo_c = head[1];
        cu.t_hi_c = head[2];
        for (uint32_t k = 0; k < FW_CUBIC_POWERS; k++) finite &= get_f32s(slot + 112 + 48 * k, cu.c[k], 12);
        cu.crc = get_u32(slot + 304);
        cu.present = 1;
        if (cu.crc != fw_cubic_crc(&cu)) return FW_SLOT_CORRUPT;
        if (finite && !(cu.t_lo_c < cu.t_hi_c)) return FW_SLOT_CORRUPT;
    }
    if (!finite) return FW_SLOT_NONFINITE;
    if (cal) *cal = c;
    if (cubic) *cubic = cu;
    if (generation) *generation = get_u32(slot + 8);
    return FW_SLOT_VALID;
}

void fw_nvm_boot(fw_board_t *b)
{
    uint8_t img[FW_NVM_SLOT_BYTES];
    fw_cal_t c;
    fw_cubic_t cu;
    uint32_t gen;
    fw_cal_zero(&b->cal);
    memset(&b->cubic, 0, sizeof b->cubic);
    b->nvm_slot = -1;
    b->nvm_seq = 0;
    b->nvm_corrupt_mask = 0;
    b->nvm_bad_nonfinite = 0;
    for (uint32_t k = 0; k < FW_NVM_SLOTS; k++) {
        fw_slot_state_t st = FW_SLOT_CORRUPT;
        if (b->hal->nvm_read && b->hal->nvm_read(b->hal->ctx, k, img, FW_NVM_SLOT_BYTES) == 0)
            st = fw_nvm_decode_rec(img, FW_NVM_SLOT_BYTES, &c, &cu, &gen);
        if (st == FW_SLOT_CORRUPT || st == FW_SLOT_NONFINITE) {
            b->nvm_corrupt_mask |= (uint8_t)(1u << k);
            if (st == FW_SLOT_NONFINITE) b->nvm_bad_nonfinite |= (uint8_t)(1u << k);
        } else if (st == FW_SLOT_VALID && (b->nvm_slot < 0 || gen > b->nvm_seq)) {
            b->cal = c;
            b->cubic = cu;
            b->nvm_seq = gen;
            b->nvm_slot = (int8_t)k;
        }
    }
    if (b->nvm_slot >= 0) b->nvm_status = FW_NVM_OK;
    else b->nvm_status = b->nvm_corrupt_mask ? FW_NVM_CORRUPT : FW_NVM_EMPTY;
}

int fw_nvm_store_rec(fw_board_t *b, const fw_cal_t *cal, const fw_cubic_t *cubic)
{
    uint8_t rec[FW_NVM_RECORD_MAX], img[FW_NVM_SLOT_BYTES];
    fw_cal_t c;
    fw_cubic_t cu;
    uint32_t slot = b->nvm_slot == 0 ? 1u : 0u, gen = b->nvm_seq + 1u, got_gen = 0;
    uint32_t len = fw_nvm_encode_rec(cal, cubic, gen, rec);
    fw_slot_state_t st = FW_SLOT_CORRUPT;
    int wrote = b->hal->nvm_write && b->hal->nvm_write(b->hal->ctx, slot, rec, len) == 0;
    int read = b->hal->nvm_read && b->hal->nvm_read(b->hal->ctx, slot, img, FW_NVM_SLOT_BYTES) == 0;
    if (read) st = fw_nvm_decode_rec(img, FW_NVM_SLOT_BYTES, &c, &cu, &got_gen);
    if (wrote && read && memcmp(img, rec, len) == 0 && st == FW_SLOT_VALID && got_gen == gen) {
        b->cal = c;   /* what the flash holds now, read back */
        b->cubic = cu;
        b->nvm_seq = gen;
        b->nvm_slot = (int8_t)slot;
        b->nvm_corrupt_mask &= (uint8_t)~(1u << slot);
        b->nvm_bad_nonfinite &= (uint8_t)~(1u << slot);
        b->nvm_status = FW_NVM_OK;
        return 0;
    }
    /* Failed: the record in force stays, the slot holds whatever the flash left. The record state
     * follows that slot as at boot (contract: `ok` only while the other slot is erased or valid), so
     * the board says now what it would say after a restart. */
    if (st == FW_SLOT_CORRUPT || st == FW_SLOT_NONFINITE) {
        b->nvm_corrupt_mask |= (uint8_t)(1u << slot);
        if (st == FW_SLOT_NONFINITE) b->nvm_bad_nonfinite |= (uint8_t)(1u << slot);
        else b->nvm_bad_nonfinite &= (uint8_t)~(1u << slot);
    } else {
        b->nvm_corrupt_mask &= (uint8_t)~(1u << slot);
        b->nvm_bad_nonfinite &= (uint8_t)~(1u << slot);
    }
    if (b->nvm_slot < 0) b->nvm_status = b->nvm_corrupt_mask ? FW_NVM_CORRUPT : FW_NVM_EMPTY;
    return -1;
}

int fw_nvm_store(fw_board_t *b, const fw_cal_t *cal)
{
    fw_cubic_t keep = b->cubic;   /* a copy: the store overwrites b->cubic with what it read back */
    return fw_nvm_store_rec(b, cal, &keep);
}
