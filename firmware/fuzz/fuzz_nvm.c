/* fuzz_nvm.c: what the board makes of its flash at boot, then commands on top of it.
 *
 * Input: [cfg][slot 0][slot 1][stream], each slot FW_NVM_SLOT_BYTES (512) bytes (missing slot bytes
 * read erased, 0xFF).
 * cfg bit 0/1: recompute the CRCs of slot 0/1 (fz_fix_record_crcs: fuzzed coefficients then reach
 * the decoder's value checks), bit 2: CAN board (node 5; stream = fz_run_can_stream) else serial
 * (stream = fz_run_serial_stream with fixed checksums), bit 3 identity, bits 4-7 the flash faults of
 * the first writes (fault of write k = bits 4-7 rotated by k). Boot from the two images, then the
 * stream, then a power cycle. Invariants: fuzz_common.h. */
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
    memset(rig.nvm.slot, 0xFF, sizeof rig.nvm.slot);
    size_t img = sizeof rig.nvm.slot;
    size_t take = size < img ? size : img;
    memcpy(rig.nvm.slot, data, take);
    data += take;
    size -= take;
    if (cfg & 1u) fz_fix_record_crcs(rig.nvm.slot[0]);
    if (cfg & 2u) fz_fix_record_crcs(rig.nvm.slot[1]);
    for (uint32_t k = 0; k < sizeof rig.nvm.fault_plan; k++)
        rig.nvm.fault_plan[k] = (uint8_t)(((uint32_t)cfg >> (4u + (k % 4u))) & 0x7u);
    fz_identity((cfg >> 3) & 1u, &id);
    uint8_t node = cfg & 4u ? 5u : 0u;
    fz_boot(&rig, &id, node, 1);
    if (node) {
        static const uint8_t IDENT[1] = { 0x03 }, START[1] = { 0x01 }, READ[1] = { 0x07 };
        fw_can_rx(&rig.board, 0x605u, 1, IDENT);
        fw_can_rx(&rig.board, 0x605u, 1, READ);
        fw_can_rx(&rig.board, 0x605u, 1, START);
        fz_check_board(&rig, "identify, CAL_READ, start");
        fz_run_can_stream(&rig, data, size);
    } else {
        fz_command(&rig, "ID");
        fz_command(&rig, "CALR");
        fz_command(&rig, "SFER");
        fz_command(&rig, "START");
        fz_run_serial_stream(&rig, data, size, 1);
    }
    fz_reboot(&rig);
    return 0;
}
