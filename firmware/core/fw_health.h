/* fw_health.h: the sensor's liveness, as a pure decision (no register, no clock of its own).
 *
 * Why: a MEMS part can reset itself (a supply glitch, ESD on the cable) and come back in power-down
 * with its registers at their defaults: it still answers on SPI but never raises data-ready again.
 * Nothing else on the board notices: the main loop waits, the station sees a silent stream. So,
 * while the station has the board streaming, every target asks this module, from a periodic tick,
 * whether the silence since the last data-ready is still normal:
 *
 *   FW_HEALTH_OK       silence within the deadline (or not streaming: the check is disarmed)
 *   FW_HEALTH_SUSPECT  the deadline passed: check WHO_AM_I now and report the answer
 *                      (fw_health_who_am_i); the next poll says REINIT
 *   FW_HEALTH_REINIT   re-initialise the sensor, then call fw_health_reinit_done and
 *                      fw_board_sensor_reinit (E,SENSOR + identity sensor_reinit=)
 *
 * Deadline = max(3 output periods + slack_us, min_silence_us), doubled for every re-init in a row
 * that brought no data-ready (at most 16x), so a part that is gone is retried, not hammered:
 *   slack_us        data-ready arrives in batches (a FIFO watermark of W samples: W source periods)
 *   min_silence_us  the link delivers samples in bursts (the simulator's sensor bridge)
 * Times are the board's uint32 microsecond clock; every difference is taken modulo 2^32.
 */
#ifndef FW_HEALTH_H
#define FW_HEALTH_H

#include <stdint.h>

#define FW_HEALTH_PERIODS 3u        /* no data-ready within this many output periods: silent */
#define FW_HEALTH_BACKOFF_MAX 4u    /* deadline x 2^4 at most after re-inits in a row */

typedef enum { FW_HEALTH_OK = 0, FW_HEALTH_SUSPECT = 1, FW_HEALTH_REINIT = 2 } fw_health_verdict_t;

typedef struct fw_health {
    uint32_t slack_us;
    uint32_t min_silence_us;
    uint32_t last_us;          /* the last data-ready (or the arming, or the last re-init) */
    uint32_t last_drdy_us;     /* the last real data-ready (the silence E,SENSOR reports) */
    uint32_t reinits_in_row;   /* re-inits since the last data-ready */
    uint32_t reinits;          /* re-inits since fw_health_init */
    uint8_t armed;             /* streaming: the check runs */
    uint8_t suspect;           /* the deadline passed: WHO_AM_I asked for */
    uint8_t who_am_i_ok;       /* its answer (1: the part answered with its own id) */
    uint8_t have_drdy;         /* last_drdy_us is valid */
} fw_health_t;

void fw_health_init(fw_health_t *h, uint32_t slack_us, uint32_t min_silence_us);
/* A data-ready happened at t_us (a sample taken, or the newest of a FIFO batch). */
void fw_health_data_ready(fw_health_t *h, uint32_t t_us);
/* The verdict at now_us for an output period of period_us; streaming 0 disarms the check (a stop
 * is no silence), and the first poll while streaming arms it with now_us as the reference. */
fw_health_verdict_t fw_health_poll(fw_health_t *h, uint32_t now_us, uint32_t period_us, int streaming);
/* After SUSPECT: did WHO_AM_I answer with the part's id? (kept for the target's message) */
void fw_health_who_am_i(fw_health_t *h, int answered_ok);
/* The target re-initialised the sensor at now_us: a new deadline starts, longer (backoff). */
void fw_health_reinit_done(fw_health_t *h, uint32_t now_us);
/* Milliseconds since the last real data-ready (or since arming when none came yet). */
uint32_t fw_health_silent_ms(const fw_health_t *h, uint32_t now_us);
/* The current deadline in microseconds for an output period (saturates at 0xFFFFFFFF). */
uint32_t fw_health_deadline_us(const fw_health_t *h, uint32_t period_us);

#endif
