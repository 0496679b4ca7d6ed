/* fw_board.c: boot, byte/frame intake and the per-sample path shared by both links. */
#include <string.h>
#include "fw_board_internal.h"
#include "fw_nvm.h"

uint32_t fw_board_sizeof(void) { return (uint32_t)sizeof(fw_board_t); }

uint8_t fw_can_scale(const fw_identity_t *id, float *ug_per_can_lsb)
{
    uint8_t shift = 0;
    while (shift < 16u && id->ug_per_lsb * (float)(1u << shift) * 32767.0f < 1.9e6f) shift++;
    if (ug_per_can_lsb) *ug_per_can_lsb = id->ug_per_lsb * (float)(1u << shift);
    return shift;
}

void fw_send_tx(fw_board_t *b, const fw_tx_t *t)
{
    uint8_t out[FW_TX_BODY_MAX + 5u];
    uint32_t n = fw_tx_frame(t, out, (uint32_t)sizeof out);
    if (n == 0 || !b->hal->uart_write) { b->frames_dropped++; return; }
    b->hal->uart_write(b->hal->ctx, out, n);
}

void fw_send_error(fw_board_t *b, const char *code, const char *text, const char *arg, uint32_t arg_len)
{
    fw_tx_t t;
    fw_tx_begin(&t, "E");
    fw_tx_str(&t, code);
    fw_tx_str(&t, text);
    if (arg) fw_tx_raw(&t, arg, arg_len);
    fw_send_tx(b, &t);
}

void fw_set_decimation(fw_board_t *b, uint32_t k)
{
    b->decim = k;
    b->phase = 0;
    b->odr_hz = b->id.odr_hz / (float)k;
}

/* One `E,NVM,...` per slot that is neither erased nor valid (serial boards): at boot and after the
 * identity reply while the record state is fallback or corrupt. */
void fw_send_nvm_errors(fw_board_t *b)
{
    if (b->can_node) return;
    for (uint32_t k = 0; k < FW_NVM_SLOTS; k++) {
        if (!(b->nvm_corrupt_mask & (1u << k))) continue;
        char num[2] = { (char)('0' + k), 0 };
        if (b->nvm_bad_nonfinite & (1u << k))
            fw_send_error(b, "NVM", "calibration record with a non-finite value in slot ", num, 1);
        else
            fw_send_error(b, "NVM", "calibration record CRC mismatch in slot ", num, 1);
    }
}

fw_rec_state_t fw_board_rec_state(const fw_board_t *b)
{
    if (b->nvm_slot >= 0) return b->nvm_corrupt_mask ? FW_REC_FALLBACK : FW_REC_OK;
    return b->nvm_status == FW_NVM_CORRUPT ? FW_REC_CORRUPT : FW_REC_EMPTY;
}

uint8_t fw_board_rec_version(const fw_board_t *b)
{
    if (b->nvm_slot < 0) return 0;
    return b->cubic.present ? 2u : 1u;
}

void fw_board_init(fw_board_t *b, const fw_hal_t *hal, const fw_identity_t *id, uint8_t can_node)
{
    memset(b, 0, sizeof *b);
    b->hal = hal;
    b->id = *id;
    b->id.serial[FW_SERIAL_MAX] = 0;
    b->id.sensor[FW_SENSOR_MAX] = 0;
    b->id.fw[FW_FW_MAX] = 0;
    b->can_node = can_node;
    fw_set_decimation(b, 1);
    b->can_shift = fw_can_scale(&b->id, &b->can_ug_per_lsb);
    /* per-sample constants, computed once (no division on the per-sample path) */
    b->counts_per_g = 1e6f / b->id.ug_per_lsb;
    b->src_rate_per_us = b->id.odr_hz * 1e-6f;
    float gap = b->id.odr_hz > 0.0f ? 1.5e6f / b->id.odr_hz : 4e9f;
    b->gap_us = gap >= 2e9f ? 0x7FFFFFFEu : (uint32_t)gap;
    b->gap_lo = 0;                      /* the first sample takes the slow path once, to arm the window */
    b->gap_span = 0xFFFFFFFFu;
    fw_selfcal_reset(&b->selfcal);
    fw_nvm_boot(b);
    fw_send_nvm_errors(b);
}

static void serial_line(fw_board_t *b, const uint8_t *line, uint32_t len)
{
    uint32_t dollar = len;
    const uint8_t *body;
    while (dollar > 0 && line[dollar - 1] != '$') dollar--;
    if (dollar == 0) { b->rx_bad_frames++; return; }      /* no frame at all: garbage */
    dollar--;
    if (dollar > 0) b->rx_bad_frames++;                   /* garbage before the frame */
    int32_t n = fw_unframe(line + dollar, len - dollar, &body);
    if (n < 0) { b->rx_bad_frames++; return; }
    fw_serial_command(b, body, (uint32_t)n);
}

void fw_uart_rx(fw_board_t *b, const uint8_t *data, uint32_t len)
{
    if (b->can_node) return;
    for (uint32_t i = 0; i < len; i++) {
        const uint8_t *line;
        uint32_t n;
        int r = fw_line_push(b->rx_line, FW_RX_LINE_MAX, &b->rx_len, &b->rx_overflow, data[i], &line, &n);
        if (r < 0) b->rx_bad_frames++;
        else if (r > 0) serial_line(b, line, n);
    }
}

void fw_can_rx(fw_board_t *b, uint16_t id, uint8_t dlc, const uint8_t *data)
{
    if (!b->can_node || id != 0x600u + b->can_node) return;
    if (dlc > 8) dlc = 8;
    fw_can_command(b, dlc, data);
}

/* Data-ready periods the board missed (t_us gap > 1.5 source periods): advance the decimation phase
 * over them and seq for each output sample among them, with no frame (contract v2: seq counts
 * samples taken). Runs only on a gap, so its divisions never touch the regular per-sample path. */
static void skip_missed(fw_board_t *b, uint32_t dt_us)
{
    if (b->gap_span == 0xFFFFFFFFu) {   /* the first sample since boot: no previous one to miss from */
        b->gap_lo = b->gap_us + 1u;
        b->gap_span = 0x7FFFFFFEu - b->gap_us;   /* dt_us - gap_lo <= gap_span: dt_us < 2^31 */
        return;
    }
    float periods = (float)dt_us * b->src_rate_per_us + 0.5f;
    uint32_t n = periods >= 4294967040.0f ? 0xFFFFFF00u : (uint32_t)periods;
    if (n < 2u) return;
    n -= 1u;                                  /* source periods missed between the two samples */
    uint32_t outputs;
    if (b->decim <= 1u) {
        outputs = n;
    } else {
        uint32_t first = b->phase == 0 ? 0u : b->decim - b->phase;   /* missed period of the first output */
        if (first >= n) {
            outputs = 0;
            b->phase += n;
            if (b->phase >= b->decim) b->phase = 0;
        } else {
            outputs = 1u + (n - 1u - first) / b->decim;
            b->phase = (n - first) % b->decim;
        }
    }
    if (b->streaming) b->seq += outputs;
}

void fw_sample(fw_board_t *b, const fw_raw_sample_t *s)
{
    uint32_t dt_us = s->t_us - b->prev_t_us;        /* wraps with the board clock */
    b->prev_t_us = s->t_us;
    /* gap_lo <= dt_us < 2^31 in one compare (a clock that went back, or jumped 2^31 us or more, is
     * no gap); until the first sample the window is everything and skip_missed only arms it */
    if (dt_us - b->gap_lo <= b->gap_span) skip_missed(b, dt_us);
    int emit = b->phase == 0;
    if (++b->phase >= b->decim) b->phase = 0;
    if (emit) {
        int segment = 0;
        if (b->selfcal_on) {
            fw_selfcal_scale_t sc = { b->id.ug_per_lsb * 1e-6f, b->id.t_lsb_per_c, b->id.t_lsb_at_25c };
            if (fw_selfcal_update(&b->selfcal, s->t_us, s->acc, s->temp, &sc) == 1 && b->selfcal.n_seg > 0
                && !b->can_node) {
                fw_serial_segment(b, &b->selfcal.seg[b->selfcal.n_seg - 1u]);
                segment = 1;
            }
        }
        if (b->streaming) {
            if (b->can_node) fw_can_sample(b, s);
            else fw_serial_sample(b, s);
        }
        if (segment) return;   /* the G frame was this sample's share: a pending reply waits one sample */
    }
    if (b->reply.pending) fw_reply_step(b, FW_REPLY_STEP_VALUES);
}

void fw_board_idle(fw_board_t *b)
{
    if (b->reply.pending) fw_reply_step(b, FW_REPLY_VALUES_MAX);
}
