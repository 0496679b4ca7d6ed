/* fw_can_proto.c: design 3.2 (CAN 2.0A, node N): commands on 0x600+N, identity and calibration
 * replies on 0x580+N, samples on 0x180+N. Bytes as drivers/protocol/can_frames.py packs them.
 * docs/design.md 3.2: identity frame 11 (reset cause, record state, version,
 * generation) after frames 0..3, frames 12/13 (serial characters 15..28) when the serial is longer
 * than 14, a non-finite CAL_FIELD refused at CAL_COMMIT (status 1), seq counts samples taken. */
#include <string.h>
#include "fw_board_internal.h"
#include "fw_nvm.h"
#include "fw_num.h"

#define CAN_SAMPLE_BASE 0x180u
#define CAN_REPLY_BASE 0x580u
#define CAL_STORED 0u
#define CAL_CRC_MISMATCH 1u
#define CAL_WRITE_FAILED 2u
#define CAL_RECORD_CORRUPT 3u   /* added: CAL_READ on a board whose NVM record is corrupt */

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void send(fw_board_t *b, uint16_t base, uint8_t dlc, const uint8_t *data)
{
    if (b->hal->can_send) b->hal->can_send(b->hal->ctx, (uint16_t)(base + b->can_node), dlc, data);
}

static void send_identity(fw_board_t *b)
{
    uint8_t d[8];
    char serial[28];
    uint32_t n = 0;
    memset(serial, 0, sizeof serial);
    for (; n < 28u && b->id.serial[n]; n++) serial[n] = b->id.serial[n];
    for (uint8_t k = 0; k < 2; k++) {
        d[0] = k;
        memcpy(d + 1, serial + 7 * k, 7);
        send(b, CAN_REPLY_BASE, 8, d);
    }
    d[0] = 2;
    put_u32(d + 1, fw_f32_bits(b->can_ug_per_lsb));
    send(b, CAN_REPLY_BASE, 5, d);
    d[0] = 3;
    put_u32(d + 1, fw_f32_bits(b->odr_hz));
    send(b, CAN_REPLY_BASE, 5, d);
    d[0] = 11;
    d[1] = b->boot.cause <= FW_RESET_SOFTWARE ? b->boot.cause : (uint8_t)FW_RESET_UNKNOWN;
    d[2] = (uint8_t)fw_board_rec_state(b);
    d[3] = fw_board_rec_version(b);
    put_u32(d + 4, b->nvm_slot >= 0 ? b->nvm_seq : 0u);
    send(b, CAN_REPLY_BASE, 8, d);
    if (n > 14u) {   /* characters 15..28, NUL padded */
        for (uint8_t k = 0; k < 2; k++) {
            d[0] = (uint8_t)(12u + k);
            memcpy(d + 1, serial + 14 + 7 * k, 7);
            send(b, CAN_REPLY_BASE, 8, d);
        }
    }
}

static void send_status(fw_board_t *b, uint8_t status)
{
    uint8_t d[7] = { 4, status, b->cal.comp ? 1 : 0, 0, 0, 0, 0 };
    put_u32(d + 3, b->cal.thermal_crc);
    send(b, CAN_REPLY_BASE, 7, d);
}

static void cal_commit(fw_board_t *b, uint32_t want_crc)
{
    uint8_t status;
    fw_cal_t c = b->cal;
    int finite = 1;
    for (int i = 0; i < 6; i++) finite &= fw_f32_finite(b->can_cal_fields[i]);
    if (b->can_cal_have != 0x3Fu || !finite || fw_crc32_f32(b->can_cal_fields, 6) != want_crc) {
        status = CAL_CRC_MISMATCH;   /* a field missing, not finite, or not the values the CRC says */
    } else {
        for (int i = 0; i < 6; i++) {
            float v = b->can_cal_fields[i] + 0.0f;
            c.thermal[i] = fw_f32_bits(v) == 0x80000000u ? 0.0f : v;
        }
        c.thermal_crc = fw_crc32_f32(c.thermal, 6);
        status = fw_nvm_store(b, &c) == 0 ? CAL_STORED : CAL_WRITE_FAILED;
    }
    b->can_cal_have = 0;
    send_status(b, status);
}

static void cal_read(fw_board_t *b)
{
    uint8_t d[5];
    for (uint8_t k = 0; k < 6; k++) {
        d[0] = (uint8_t)(5u + k);
        put_u32(d + 1, fw_f32_bits(b->cal.thermal[k]));
        send(b, CAN_REPLY_BASE, 5, d);
    }
    send_status(b, b->nvm_status == FW_NVM_CORRUPT ? CAL_RECORD_CORRUPT : CAL_STORED);
}

void fw_can_command(fw_board_t *b, uint8_t dlc, const uint8_t *data)
{
    if (dlc < 1) { b->rx_bad_frames++; return; }
    switch (data[0]) {
    case 0x01: b->streaming = 1; break;
    case 0x02: b->streaming = 0; break;
    case 0x03: send_identity(b); break;
    case 0x04: {
        if (dlc < 5) { b->rx_bad_frames++; break; }
        uint32_t k = fw_rate_ratio(b->id.odr_hz, fw_bits_f32(get_u32(data + 1)));
        if (k) fw_set_decimation(b, k);   /* an unsupported rate is ignored (3.2 has no error reply) */
        break;
    }
    case 0x05:
        if (dlc < 6 || data[1] >= 6) { b->rx_bad_frames++; break; }
        b->can_cal_fields[data[1]] = fw_bits_f32(get_u32(data + 2));
        b->can_cal_have |= (uint8_t)(1u << data[1]);
        break;
    case 0x06:
        if (dlc < 5) { b->rx_bad_frames++; break; }
        cal_commit(b, get_u32(data + 1));
        break;
    case 0x07: cal_read(b); break;
    case 0x08:
        if (dlc < 2 || data[1] > 1) { b->rx_bad_frames++; break; }
        if (b->nvm_status != FW_NVM_CORRUPT && b->cal.comp != data[1]) {   /* no reply in 3.2 */
            fw_cal_t c = b->cal;
            c.comp = data[1];
            (void)fw_nvm_store(b, &c);
        }
        break;
    default: b->rx_bad_frames++; break;
    }
}

void fw_can_sample(fw_board_t *b, const fw_raw_sample_t *s)
{
    int32_t acc[3] = { s->acc[0], s->acc[1], s->acc[2] };
    float temp_c = fw_temp_c(&b->id, s->temp);
    if (b->cal.comp) fw_apply_comp(b, s, temp_c, acc);
    uint8_t d[8];
    for (int i = 0; i < 3; i++) {
        int64_t v = acc[i];
        if (b->can_shift) {   /* floor((v + half) / 2^shift): round half up, as can_scale users do */
            int64_t q = v + ((int64_t)1 << (b->can_shift - 1u));
            v = q >= 0 ? q >> b->can_shift : -((-q + ((int64_t)1 << b->can_shift) - 1) >> b->can_shift);
        }
        if (v > 32767) v = 32767;
        if (v < -32768) v = -32768;
        uint16_t u = (uint16_t)(int16_t)v;
        d[2 * i] = (uint8_t)u;
        d[2 * i + 1] = (uint8_t)(u >> 8);
    }
    float t = temp_c - 25.0f;   /* np.round: half to even */
    int32_t t8;
    if (!(t == t)) t8 = 0;
    else if (t >= 127.0f) t8 = 127;
    else if (t <= -128.0f) t8 = -128;
    else {
        float r = t >= 0.0f ? (t + 8388608.0f) - 8388608.0f : (t - 8388608.0f) + 8388608.0f;
        t8 = (int32_t)r;
    }
    d[6] = (uint8_t)(int8_t)t8;
    d[7] = (uint8_t)b->seq;   /* 8-bit: the low byte of the samples-taken count (missed ones included) */
    send(b, CAN_SAMPLE_BASE, 8, d);
    b->seq++;
}
