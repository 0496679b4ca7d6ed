/* fuzz_bridge.c: the sensor bridge lines (fw_bridge.c) as the host and QEMU targets use them.
 *
 * Input: [cfg][bytes]. Bytes go through fw_linebuf_push; every complete line to fw_bridge_line (and,
 * when that says NONE, fw_bridge_fault). The first identity boots the board (fw_board_init with the
 * parsed identity; cfg bit 2: every identity re-boots it, as after a reset) from NVM preset cfg
 * bits 0-1, then `$ID`, `$COMP,1`, `$START` (cfg bit 3: `$SCAL,1` too); every sample goes to
 * fw_sample. cfg bit 4: fix the `*HH` of every line first. Besides the common invariants, what
 * fw_bridge_line promises: a parsed identity has NUL-terminated non-empty serial and sensor,
 * finite scalings, ug_per_lsb > 0, odr_hz > 0, t_lsb_per_c != 0. */
#include <string.h>
#include "fuzz_common.h"
#include "fw_bridge.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

static int finite(float v) { return v - v == 0.0f; }

static void check_identity(const fw_identity_t *id)
{
    if (memchr(id->serial, 0, sizeof id->serial) == NULL || id->serial[0] == 0)
        fz_violation("bridge identity", "serial not a NUL-terminated non-empty string", "fw_bridge_line");
    if (memchr(id->sensor, 0, sizeof id->sensor) == NULL || id->sensor[0] == 0)
        fz_violation("bridge identity", "sensor not a NUL-terminated non-empty string", "fw_bridge_line");
    if (!finite(id->ug_per_lsb) || !finite(id->t_lsb_per_c) || !finite(id->t_lsb_at_25c) || !finite(id->odr_hz)
        || !(id->ug_per_lsb > 0.0f) || !(id->odr_hz > 0.0f) || id->t_lsb_per_c == 0.0f)
        fz_violation("bridge identity", "scaling out of its contract", "fw_bridge_line");
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static fz_rig_t rig;
    static fw_linebuf_t lb;
    int booted = 0;
    if (size < 1u) return 0;
    uint8_t cfg = data[0];
    memset(&rig, 0, sizeof rig);
    memset(&lb, 0, sizeof lb);
    fz_nvm_preset(&rig.nvm, cfg & 3u);
    for (size_t i = 1; i < size; i++) {
        const uint8_t *line;
        uint32_t len;
        if (fw_linebuf_push(&lb, data[i], &line, &len) != 1) continue;
        uint8_t copy[sizeof lb.buf];
        if (len > sizeof copy) fz_violation("line buffer", "line longer than its buffer", "fw_linebuf_push");
        memcpy(copy, line, len);
        if (cfg & 0x10u) fz_fix_line_checksum(copy, len && copy[len - 1] == '\r' ? len - 1u : len);
        fw_identity_t id;
        fw_raw_sample_t s;
        int kind = fw_bridge_line(copy, len, &id, &s);
        if (kind == FW_BRIDGE_IDENTITY) {
            check_identity(&id);
            if (booted && !(cfg & 4u)) continue;
            fz_boot(&rig, &id, 0, 1);
            booted = 1;
            fz_command(&rig, "ID");
            fz_command(&rig, "COMP,1");
            if (cfg & 8u) fz_command(&rig, "SCAL,1");
            fz_command(&rig, "START");
        } else if (kind == FW_BRIDGE_SAMPLE) {
            if (!booted) continue;
            fw_sample(&rig.board, &s);
            fz_check_board(&rig, "fw_sample of a bridge sample");
        } else if (kind == FW_BRIDGE_NONE) {
            fw_bridge_fault_t x;
            if (fw_bridge_fault(copy, len, &x) == FW_BRIDGE_FAULT && booted && x.kind == FW_FAULT_SELFCAL_SKEW) {
                if (!finite(x.value)) fz_violation("bridge fault", "selfcal_skew value not finite", "fw_bridge_fault");
                fw_board_selfcal_skew(&rig.board, x.value);
                fz_check_board(&rig, "fw_board_selfcal_skew");
            }
        }
    }
    if (booted) {
        fz_command(&rig, "SCRR");
        fz_reboot(&rig);
    }
    return 0;
}
