/* fuzz_can.c: the CAN link (design 3.2) of a board already identified and streaming.
 *
 * Input: [cfg][node][records]. cfg bit 0 identity, bits 1-2 NVM preset, bits 4-6 reset cause,
 * bit 7 flash faults (plan from the first record bytes); node: the board's node id (1..127).
 * records: fz_run_can_stream ((id, dlc, data) frames for fw_can_rx, sample records). The board is
 * power cycled from the RAM NVM at the end. Invariants: fuzz_common.h. */
#include <string.h>
#include "fuzz_common.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static fz_rig_t rig;
    static const uint8_t IDENT[1] = { 0x03 }, START[1] = { 0x01 };
    fw_identity_t id;
    if (size < 2u) return 0;
    uint8_t cfg = data[0], node = (uint8_t)(1u + data[1] % 127u);
    data += 2;
    size -= 2;
    memset(&rig, 0, sizeof rig);
    fz_nvm_preset(&rig.nvm, (uint32_t)(cfg >> 1) & 3u);
    if (cfg & 0x80u) for (size_t k = 0; k < sizeof rig.nvm.fault_plan && k < size; k++) rig.nvm.fault_plan[k] = data[k];
    fz_identity(cfg & 1u, &id);
    fz_boot(&rig, &id, node, (uint8_t)((cfg >> 4) & 7u));
    fw_can_rx(&rig.board, (uint16_t)(0x600u + node), 1, IDENT);
    fw_can_rx(&rig.board, (uint16_t)(0x600u + node), 1, START);
    fz_check_board(&rig, "identify and start");
    fz_run_can_stream(&rig, data, size);
    fz_reboot(&rig);
    return 0;
}
