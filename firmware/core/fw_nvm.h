/* fw_nvm.h: the calibration record in non-volatile memory, two slots A/B (slot 0, slot 1).
 *
 * Record layout (little-endian, FW_NVM_RECORD_BYTES bytes at the start of a slot; the rest of the
 * slot stays erased 0xFF):
 *   off  size  field
 *     0     4  magic 0x4C414346 ("FCAL" in memory)
 *     4     2  layout version (1)
 *     6     2  record length in bytes (104)
 *     8     4  generation counter (1 for the first record ever written, +1 per write)
 *    12    24  thermal[6] float32: tdb x y z (mg/C), tdsf x y z (ppm/C)
 *    36     4  thermal_crc: CRC-32 (zlib) of thermal[] (design 3.1, = Python crc32_f32)
 *    40     1  has_sfem (0/1), 41..43 zero
 *    44    48  sfem[12] float32: a11..a33 row by row, b x y z (g); zeros when has_sfem is 0
 *    92     4  sfem_crc: CRC-32 of sfem[] when has_sfem, else 0
 *    96     1  comp (0/1), 97..99 zero
 *   100     4  record CRC-32 of bytes 0..99, written last in the layout
 * A slot is ERASED when every one of its FW_NVM_SLOT_BYTES bytes reads 0xFF, VALID when magic,
 * version, length, both value CRCs, the flags and the record CRC check, else CORRUPT.
 * Writes go to the slot NOT holding the newest valid record, with generation + 1, and are read
 * back and checked; boot applies the valid record with the highest generation, so a write torn by
 * a power loss leaves the previous record in force.
 */
#ifndef FW_NVM_H
#define FW_NVM_H

#include <stdint.h>
#include "fw_board.h"

#define FW_NVM_MAGIC 0x4C414346u
#define FW_NVM_VERSION 1u
#define FW_NVM_RECORD_BYTES 104u

typedef enum { FW_SLOT_ERASED = 0, FW_SLOT_VALID = 1, FW_SLOT_CORRUPT = 2 } fw_slot_state_t;

void fw_cal_zero(fw_cal_t *cal);   /* virgin board: zeros, CRC of the zeros, no SFEM, comp off */
void fw_nvm_encode(const fw_cal_t *cal, uint32_t generation, uint8_t out[FW_NVM_RECORD_BYTES]);
/* Decode one slot image of len bytes (>= FW_NVM_RECORD_BYTES): cal/generation set when VALID. */
fw_slot_state_t fw_nvm_decode(const uint8_t *slot, uint32_t len, fw_cal_t *cal, uint32_t *generation);
/* Boot: read both slots, apply the newest valid record to b->cal (zeros when none) and set
 * b->nvm_status, b->nvm_seq, b->nvm_slot, b->nvm_corrupt_mask. */
void fw_nvm_boot(fw_board_t *b);
/* Store cal as a new record (other slot, generation + 1, read back). 0 on success (then b->cal,
 * b->nvm_* are updated and the status is OK), -1 on a failed write (b unchanged). */
int fw_nvm_store(fw_board_t *b, const fw_cal_t *cal);

#endif
