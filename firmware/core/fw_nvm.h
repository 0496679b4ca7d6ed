/* fw_nvm.h: the calibration record in non-volatile memory, two slots A/B (slot 0, slot 1).
 *
 * Record layout (little-endian, at the start of a slot of FW_NVM_SLOT_BYTES; the rest of the slot
 * stays erased 0xFF). Version 1 (104 bytes) is written while no cubic SFEM is stored, version 2
 * (312 bytes) once one is: a version-2 record is a version-1 record with the cubic SFEM after it.
 *   off  size  field
 *     0     4  magic 0x4C414346 ("FCAL" in memory)
 *     4     2  layout version (1 or 2)
 *     6     2  record length in bytes (104 for version 1, 312 for version 2)
 *     8     4  generation counter (1 for the first record ever written, +1 per write)
 *    12    24  thermal[6] float32: tdb x y z (mg/C), tdsf x y z (ppm/C)
 *    36     4  thermal_crc: CRC-32 (zlib) of thermal[] (design 3.1, = Python crc32_f32)
 *    40     1  has_sfem (0/1), 41..43 zero
 *    44    48  sfem[12] float32: a11..a33 row by row, b x y z (g); zeros when has_sfem is 0
 *    92     4  sfem_crc: CRC-32 of sfem[] when has_sfem, else 0
 *    96     1  comp (0/1), 97..99 zero
 *   version 1:
 *   100     4  record CRC-32 of bytes 0..99, written last in the layout
 *   version 2:
 *   100    12  t_ref_c, t_lo_c, t_hi_c float32 (C)
 *   112   192  c[4][12] float32, power k = 0..3 in turn, each a11..a33 row by row, b x y z (g)
 *   304     4  cubic_crc: CRC-32 of the 51 float32 t_ref_c, t_lo_c, t_hi_c, c[0..3][0..11] (= $SFTC crc)
 *   308     4  record CRC-32 of bytes 0..307
 * A slot is ERASED when every one of its FW_NVM_SLOT_BYTES bytes reads 0xFF, VALID when magic,
 * version with its length, every value CRC, the flags and the record CRC check AND every value is
 * finite (and t_lo_c < t_hi_c), else CORRUPT (NONFINITE: corrupt because a value is not finite
 * although every CRC checks: never applied either).
 * Writes go to the slot NOT holding the newest valid record, with generation + 1, and are read
 * back and checked; boot applies the valid record with the highest generation, so a write torn by
 * a power loss leaves the previous record in force (record state `fallback`: a valid record in
 * force while the other slot is neither erased nor valid, as a torn newer write leaves it).
 * A board with a version-1 record boots and applies it unchanged; a CALW/SFEW/COMP on a board whose
 * record is version 2 writes version 2 again (the cubic SFEM is kept).
 */
#ifndef FW_NVM_H
#define FW_NVM_H

#include <stdint.h>
#include "fw_board.h"

#define FW_NVM_MAGIC 0x4C414346u
#define FW_NVM_VERSION 1u             /* layout without a cubic SFEM */
#define FW_NVM_RECORD_BYTES 104u
#define FW_NVM_VERSION2 2u            /* layout with the cubic SFEM */
#define FW_NVM_RECORD2_BYTES 312u
#define FW_NVM_RECORD_MAX FW_NVM_RECORD2_BYTES

#if FW_NVM_RECORD_MAX > FW_NVM_SLOT_BYTES
#error "a version-2 record does not fit one NVM slot (fw_hal.h FW_NVM_SLOT_BYTES)"
#endif

typedef enum { FW_SLOT_ERASED = 0, FW_SLOT_VALID = 1, FW_SLOT_CORRUPT = 2, FW_SLOT_NONFINITE = 3 } fw_slot_state_t;

void fw_cal_zero(fw_cal_t *cal);   /* virgin board: zeros, CRC of the zeros, no SFEM, comp off */
/* Encode cal (and cubic when cubic && cubic->present: version 2, else version 1) into out; returns
 * the record length (FW_NVM_RECORD_BYTES or FW_NVM_RECORD2_BYTES). */
uint32_t fw_nvm_encode_rec(const fw_cal_t *cal, const fw_cubic_t *cubic, uint32_t generation,
                           uint8_t *out);   /* out: FW_NVM_RECORD_MAX bytes */
void fw_nvm_encode(const fw_cal_t *cal, uint32_t generation, uint8_t out[FW_NVM_RECORD_BYTES]);   /* version 1 */
/* Decode one slot image of len bytes: cal, cubic (present = 0 for a version-1 record) and
 * generation set when VALID; any of them may be NULL. fw_nvm_decode: the same without the cubic. */
fw_slot_state_t fw_nvm_decode_rec(const uint8_t *slot, uint32_t len, fw_cal_t *cal, fw_cubic_t *cubic,
                                  uint32_t *generation);
fw_slot_state_t fw_nvm_decode(const uint8_t *slot, uint32_t len, fw_cal_t *cal, uint32_t *generation);
/* Boot: read both slots, apply the newest valid record to b->cal / b->cubic (zeros when none) and
 * set b->nvm_status, b->nvm_seq, b->nvm_slot, b->nvm_corrupt_mask, b->nvm_bad_nonfinite. */
void fw_nvm_boot(fw_board_t *b);
/* Store cal and cubic (version 2 when cubic->present) as a new record (other slot, generation + 1,
 * read back). 0 on success (then b->cal, b->cubic, b->nvm_* are updated and the status is OK), -1
 * on a failed write (b unchanged). fw_nvm_store keeps the cubic SFEM in force (b->cubic). */
int fw_nvm_store_rec(fw_board_t *b, const fw_cal_t *cal, const fw_cubic_t *cubic);
int fw_nvm_store(fw_board_t *b, const fw_cal_t *cal);

#endif
