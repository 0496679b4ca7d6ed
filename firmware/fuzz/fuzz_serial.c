/* fuzz_serial.c: the serial link (design 3.1) of a board already identified and streaming.
 *
 * Input: [cfg][stream]. cfg bit 0 identity (fz_identity), bits 1-2 NVM preset (fz_nvm_preset),
 * bit 3 fix the `*HH` of every line (so mutated commands reach the parser), bits 4-6 the reset cause
 * the target reports, bit 7 flash faults (write k fails in the way of the stream's first bytes).
 * stream: fz_run_serial_stream (bytes for fw_uart_rx, sample records). The board is power cycled
 * from the RAM NVM at the end. Invariants: fuzz_common.h. */
#include <string.h>
#include "fuzz_common.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static fz_rig_t rig;
    fw_identity_t id;
    if (size < 1u) return 0;
    uint8_t cfg = data[0];
    data++;
    size--;
    memset(&rig, 0, sizeof rig);
    fz_nvm_preset(&rig.nvm, (uint32_t)(cfg >> 1) & 3u);
    if (cfg & 0x80u) for (size_t k = 0; k < sizeof rig.nvm.fault_plan && k < size; k++) rig.nvm.fault_plan[k] = data[k];
    fz_identity(cfg & 1u, &id);
    fz_boot(&rig, &id, 0, (uint8_t)((cfg >> 4) & 7u));
    fz_command(&rig, "ID");
    fz_command(&rig, "START");
    fz_run_serial_stream(&rig, data, size, (cfg & 0x08u) != 0);
    fz_reboot(&rig);
    return 0;
}
