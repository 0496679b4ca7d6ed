/* fw_crc32.c: CRC-32 as zlib's crc32() (reflected polynomial 0xEDB88320, init/xorout 0xFFFFFFFF),
 * and the design 3.1/3.2 CRC of float32 values (little-endian bytes, -0.0 stored as +0.0 exactly as
 * the station's cal_record.to_f32 does), also over the 51 values of the cubic SFEM ($SFTC order).
 * A 16-entry nibble table: small and fast enough. */
#include "fw_board.h"
#include "fw_num.h"

static const uint32_t crc_nibble[16] = {
    0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u, 0x4DB26158u, 0x5005713Cu,
    0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu, 0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu,
};

uint32_t fw_crc32(uint32_t crc, const uint8_t *buf, uint32_t len)
{
    crc = ~crc;
    for (uint32_t i = 0; i < len; i++) {
        crc ^= buf[i];
        crc = (crc >> 4) ^ crc_nibble[crc & 0xFu];
        crc = (crc >> 4) ^ crc_nibble[crc & 0xFu];
    }
    return ~crc;
}

static uint32_t crc_f32_more(uint32_t crc, const float *values, uint32_t n)
{
    for (uint32_t i = 0; i < n; i++) {
        uint32_t u = fw_f32_bits(values[i]);
        if (u == 0x80000000u) u = 0;   /* -0.0 -> +0.0 (to_f32 adds 0.0) */
        uint8_t le[4] = { (uint8_t)u, (uint8_t)(u >> 8), (uint8_t)(u >> 16), (uint8_t)(u >> 24) };
        crc = fw_crc32(crc, le, 4);
    }
    return crc;
}

uint32_t fw_crc32_f32(const float *values, uint32_t n) { return crc_f32_more(0, values, n); }

uint32_t fw_cubic_crc(const fw_cubic_t *cu)
{
    const float head[3] = { cu->t_ref_c, cu->t_lo_c, cu->t_hi_c };
    uint32_t crc = crc_f32_more(0, head, 3);
    for (uint32_t k = 0; k < FW_CUBIC_POWERS; k++) crc = crc_f32_more(crc, cu->c[k], 12);
    return crc;
}
