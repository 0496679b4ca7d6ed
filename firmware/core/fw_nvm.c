/* fw_nvm.c: calibration record layout, A/B slots, boot selection (layout in fw_nvm.h). */
#include <string.h>
#include "fw_nvm.h"
#include "fw_num.h"

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

void fw_cal_zero(fw_cal_t *cal)
{
    memset(cal, 0, sizeof *cal);
    cal->thermal_crc = fw_crc32_f32(cal->thermal, 6);
}

void fw_nvm_encode(const fw_cal_t *cal, uint32_t generation, uint8_t out[FW_NVM_RECORD_BYTES])
{
    memset(out, 0, FW_NVM_RECORD_BYTES);
    put_u32(out, FW_NVM_MAGIC);
    out[4] = (uint8_t)FW_NVM_VERSION;
    out[6] = (uint8_t)FW_NVM_RECORD_BYTES;
    put_u32(out + 8, generation);
    for (uint32_t i = 0; i < 6; i++) put_u32(out + 12 + 4 * i, fw_f32_bits(cal->thermal[i]));
    put_u32(out + 36, cal->thermal_crc);
    out[40] = cal->has_sfem ? 1 : 0;
    if (cal->has_sfem) {
        for (uint32_t i = 0; i < 12; i++) put_u32(out + 44 + 4 * i, fw_f32_bits(cal->sfem[i]));
        put_u32(out + 92, cal->sfem_crc);
    }
    out[96] = cal->comp ? 1 : 0;
    put_u32(out + 100, fw_crc32(0, out, 100));
}

fw_slot_state_t fw_nvm_decode(const uint8_t *slot, uint32_t len, fw_cal_t *cal, uint32_t *generation)
{
    uint32_t i;
    for (i = 0; i < len && slot[i] == 0xFFu; i++) {}
    if (i == len) return FW_SLOT_ERASED;
    if (len < FW_NVM_RECORD_BYTES || get_u32(slot) != FW_NVM_MAGIC || slot[4] != FW_NVM_VERSION || slot[5] != 0
        || slot[6] != FW_NVM_RECORD_BYTES || slot[7] != 0 || get_u32(slot + 100) != fw_crc32(0, slot, 100)
        || slot[40] > 1 || slot[96] > 1)
        return FW_SLOT_CORRUPT;
    fw_cal_t c;
    memset(&c, 0, sizeof c);
    for (i = 0; i < 6; i++) c.thermal[i] = fw_bits_f32(get_u32(slot + 12 + 4 * i));
    c.thermal_crc = get_u32(slot + 36);
    c.has_sfem = slot[40];
    for (i = 0; i < 12; i++) c.sfem[i] = fw_bits_f32(get_u32(slot + 44 + 4 * i));
    c.sfem_crc = get_u32(slot + 92);
    c.comp = slot[96];
    if (c.thermal_crc != fw_crc32_f32(c.thermal, 6)) return FW_SLOT_CORRUPT;
    if (c.has_sfem ? c.sfem_crc != fw_crc32_f32(c.sfem, 12) : c.sfem_crc != 0) return FW_SLOT_CORRUPT;
    *cal = c;
    *generation = get_u32(slot + 8);
    return FW_SLOT_VALID;
}

void fw_nvm_boot(fw_board_t *b)
{
    uint8_t img[FW_NVM_SLOT_BYTES];
    fw_cal_t c;
    uint32_t gen;
    fw_cal_zero(&b->cal);
    b->nvm_slot = -1;
    b->nvm_seq = 0;
    b->nvm_corrupt_mask = 0;
    for (uint32_t k = 0; k < FW_NVM_SLOTS; k++) {
        fw_slot_state_t st = FW_SLOT_CORRUPT;
        if (b->hal->nvm_read && b->hal->nvm_read(b->hal->ctx, k, img, FW_NVM_SLOT_BYTES) == 0)
            st = fw_nvm_decode(img, FW_NVM_SLOT_BYTES, &c, &gen);
        if (st == FW_SLOT_CORRUPT) b->nvm_corrupt_mask |= (uint8_t)(1u << k);
        else if (st == FW_SLOT_VALID && (b->nvm_slot < 0 || gen > b->nvm_seq)) {
            b->cal = c;
            b->nvm_seq = gen;
            b->nvm_slot = (int8_t)k;
        }
    }
    if (b->nvm_slot >= 0) b->nvm_status = FW_NVM_OK;
    else b->nvm_status = b->nvm_corrupt_mask ? FW_NVM_CORRUPT : FW_NVM_EMPTY;
}

int fw_nvm_store(fw_board_t *b, const fw_cal_t *cal)
{
    uint8_t rec[FW_NVM_RECORD_BYTES], img[FW_NVM_SLOT_BYTES];
    uint32_t slot = b->nvm_slot == 0 ? 1u : 0u, gen = b->nvm_seq + 1u, got_gen;
    fw_cal_t back;
    fw_nvm_encode(cal, gen, rec);
    if (!b->hal->nvm_write || b->hal->nvm_write(b->hal->ctx, slot, rec, FW_NVM_RECORD_BYTES) != 0) return -1;
    if (!b->hal->nvm_read || b->hal->nvm_read(b->hal->ctx, slot, img, FW_NVM_SLOT_BYTES) != 0) return -1;
    if (fw_nvm_decode(img, FW_NVM_SLOT_BYTES, &back, &got_gen) != FW_SLOT_VALID || got_gen != gen
        || memcmp(img, rec, FW_NVM_RECORD_BYTES) != 0)
        return -1;
    b->cal = back;
    b->nvm_seq = gen;
    b->nvm_slot = (int8_t)slot;
    b->nvm_corrupt_mask &= (uint8_t)~(1u << slot);
    b->nvm_status = FW_NVM_OK;
    return 0;
}
