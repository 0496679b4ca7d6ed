/* fw_boot.c: boot facts and sensor health as the core reports them (fw_boot.h). */
#include "fw_board.h"
#include "fw_board_internal.h"
#include "fw_num.h"

static const char *const RESET_WORDS[] = { "unknown", "power", "pin", "watchdog", "fault", "brownout", "software" };

const char *fw_reset_word(uint8_t cause)
{
    return cause < sizeof RESET_WORDS / sizeof RESET_WORDS[0] ? RESET_WORDS[cause] : RESET_WORDS[0];
}

void fw_board_set_boot(fw_board_t *b, const fw_boot_info_t *boot)
{
    b->boot = *boot;
}

void fw_board_sensor_reinit(fw_board_t *b, uint32_t silent_ms)
{
    char num[12];
    b->sensor_reinits++;
    if (b->can_node) return;
    uint32_t n = fw_fmt_u32(num, silent_ms);
    fw_send_error(b, "SENSOR", "no data-ready for ", num, n);
}

int fw_board_streaming(const fw_board_t *b) { return b->streaming != 0; }

uint32_t fw_board_period_us(const fw_board_t *b)
{
    float hz = b->odr_hz > 0.0f ? b->odr_hz : 1.0f;
    float us = 1e6f / hz;
    return us >= 4e9f ? 4000000000u : (uint32_t)us;
}

void fw_board_selfcal_skew(fw_board_t *b, float tdb_mg_per_c) { b->selfcal_skew_mg_per_c = tdb_mg_per_c; }

uint32_t fw_serial_from_uid(const uint8_t uid[12], char *out)
{
    static const char HEX[] = "0123456789ABCDEF";
    uint32_t n = 0;
    out[n++] = 'F';
    out[n++] = '4';
    for (uint32_t i = 0; i < 12u; i++) {
        out[n++] = HEX[uid[i] >> 4];
        out[n++] = HEX[uid[i] & 15u];
    }
    out[n] = 0;
    return n;
}
