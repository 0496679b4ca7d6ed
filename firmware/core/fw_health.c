/* fw_health.c: the sensor's liveness decision (see fw_health.h). */
#include <string.h>
#include "fw_health.h"

void fw_health_init(fw_health_t *h, uint32_t slack_us, uint32_t min_silence_us)
{
    memset(h, 0, sizeof *h);
    h->slack_us = slack_us;
    h->min_silence_us = min_silence_us;
}

void fw_health_data_ready(fw_health_t *h, uint32_t t_us)
{
    h->last_us = t_us;
    h->last_drdy_us = t_us;
    h->have_drdy = 1u;
    h->reinits_in_row = 0u;
    h->suspect = 0u;
}

uint32_t fw_health_deadline_us(const fw_health_t *h, uint32_t period_us)
{
    uint64_t d = (uint64_t)period_us * FW_HEALTH_PERIODS + h->slack_us;
    uint32_t shift = h->reinits_in_row < FW_HEALTH_BACKOFF_MAX ? h->reinits_in_row : FW_HEALTH_BACKOFF_MAX;
    if (d < h->min_silence_us) d = h->min_silence_us;
    d <<= shift;
    return d > 0xFFFFFFFFu ? 0xFFFFFFFFu : (uint32_t)d;
}

fw_health_verdict_t fw_health_poll(fw_health_t *h, uint32_t now_us, uint32_t period_us, int streaming)
{
    if (!streaming) {
        h->armed = 0u;
        h->suspect = 0u;
        return FW_HEALTH_OK;
    }
    if (!h->armed) {
        /* the time stopped does not count as silence: the reference is the start of streaming */
        h->armed = 1u;
        h->suspect = 0u;
        h->last_us = now_us;
        if (!h->have_drdy) {
            h->last_drdy_us = now_us;
            h->have_drdy = 1u;
        }
        return FW_HEALTH_OK;
    }
    /* a data-ready time may lie a little ahead of now (reconstructed from a FIFO batch): silence 0 */
    uint32_t silent = now_us - h->last_us;
    if (silent > 0x80000000u || silent <= fw_health_deadline_us(h, period_us)) return FW_HEALTH_OK;
    if (!h->suspect) {
        h->suspect = 1u;
        h->who_am_i_ok = 0u;
        return FW_HEALTH_SUSPECT;
    }
    return FW_HEALTH_REINIT;
}

void fw_health_who_am_i(fw_health_t *h, int answered_ok)
{
    h->who_am_i_ok = answered_ok ? 1u : 0u;
}

void fw_health_reinit_done(fw_health_t *h, uint32_t now_us)
{
    h->last_us = now_us;
    h->suspect = 0u;
    h->reinits++;
    if (h->reinits_in_row < 0xFFFFFFFFu) h->reinits_in_row++;
}

uint32_t fw_health_silent_ms(const fw_health_t *h, uint32_t now_us)
{
    uint32_t silent = now_us - h->last_drdy_us;
    return silent > 0x80000000u ? 0u : silent / 1000u;
}
