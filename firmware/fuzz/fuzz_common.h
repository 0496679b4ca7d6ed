/* fuzz_common.h: what the four libFuzzer targets share (firmware/fuzz/README.md).
 *
 * A board runs on a RAM HAL: two NVM slots in memory (erased 0xFF), a serial or CAN sink that checks
 * every frame the board sends, and flash faults the input can schedule. After every step of an input
 * the targets call fz_check_board: it aborts (libFuzzer saves the reproducer) on an invariant
 * violation, printed as `FW_FUZZ INVARIANT VIOLATION: ...`:
 *   - a non-finite float in the applied calibration (every float field of fw_cal_t and of the
 *     version-2 cubic SFEM fw_cubic_t: fz_cal_floats, fz_cubic_floats);
 *   - an NVM write of an image fw_nvm_decode does not read back as VALID, or whose record holds a
 *     non-finite coefficient (checked on the bytes the core asked to program, before any fault);
 *   - a serial frame that is not one `$BODY*HH\n` fw_unframe accepts, a CAN frame with dlc > 8 or
 *     an identifier outside the node's reply/sample ranges.
 * Sanitizer reports (ASan, UBSan with -fno-sanitize-recover) and crashes end the run the same way.
 */
#ifndef FUZZ_COMMON_H
#define FUZZ_COMMON_H

#include <stddef.h>
#include <stdint.h>
#include "fw_board.h"
#include "fw_nvm.h"

/* Flash behaviour of one write (fz_nvm_t.fault_plan). */
enum {
    FZ_FLASH_OK = 0,
    FZ_FLASH_FAIL = 1,        /* returns -1, slot unchanged */
    FZ_FLASH_TORN_FAIL = 2,   /* programs a prefix, returns -1 (power dip seen by the driver) */
    FZ_FLASH_TORN_OK = 3,     /* programs a prefix, returns 0 (a lying flash: the read-back must catch it) */
    FZ_FLASH_FLIP = 4         /* programs all, one bit flipped, returns 0 (read-back must catch it) */
};

typedef struct fz_nvm {
    uint8_t slot[FW_NVM_SLOTS][FW_NVM_SLOT_BYTES];
    uint8_t fault_plan[8];    /* write k (k < 8) behaves as fault_plan[k]; later writes are OK */
    uint32_t writes;          /* write calls seen */
} fz_nvm_t;

typedef struct fz_rig {
    fz_nvm_t nvm;
    fw_hal_t hal;
    fw_board_t board;
    uint8_t can_node;
    uint32_t frames_out;      /* frames the board sent (serial or CAN) */
    uint32_t clock_us;        /* board time of the next generated sample */
    uint32_t samples;         /* samples fed in this input (at most FZ_SAMPLE_BUDGET) */
} fz_rig_t;

/* Samples one input may feed: enough for the on-board calibrator's four segments of 1500 (so its
 * result path is reachable), few enough that no input runs into libFuzzer's timeout on a loaded CI. */
#define FZ_SAMPLE_BUDGET 16384u

/* Identities the serial/CAN/NVM targets boot with (index & 1): LIS3DSH at 100 Hz (so ODR 50, 25,
 * 12.5 ... decimate), ADXL355 at 3.125 Hz with its negative temperature slope. */
void fz_identity(uint32_t index, fw_identity_t *id);

/* NVM contents before boot (index & 3): erased; a v1 record with thermal coefficients and COMP on;
 * a v2 record with the SFEM and the cubic SFEM too; a valid slot 0 beside a corrupt slot 1. */
void fz_nvm_preset(fz_nvm_t *n, uint32_t index);

/* Set up the RAM HAL (serial board when can_node is 0) and boot the board from rig->nvm, then check.
 * fw_board_set_boot tells it the reset cause `cause` (fw_boot.h). */
void fz_boot(fz_rig_t *rig, const fw_identity_t *id, uint8_t can_node, uint8_t cause);
/* Power cycle: boot again from the same RAM NVM with the board's identity, then check. */
void fz_reboot(fz_rig_t *rig);

/* Send the board one framed command body (`$body*HH\n` with the right checksum), then check. */
void fz_command(fz_rig_t *rig, const char *body);
/* One generated sample: accelerations, temperature count; the clock advances one source period. */
void fz_sample(fz_rig_t *rig, int32_t ax, int32_t ay, int32_t az, int32_t temp);

/* Parse-and-run helpers shared by the serial and NVM targets: a serial byte stream in which a 0x00
 * byte starts a sample record (FZ_SAMPLE_RECORD bytes after the marker: reps, temp step, 3 x int32
 * acceleration, int32 temperature; reps+1 samples, the temperature stepping by the signed step every
 * 16 samples), 0x01 a sensor re-init report (2 bytes: silent ms), any other byte run up to the next
 * marker goes to fw_uart_rx (when fix_checksums: line by line, each `$SFTC` CRC and `*HH` fixed first).
 * A fixed sample follows every byte run, so streaming and compensation run on every input. */
#define FZ_SAMPLE_RECORD 19u
void fz_run_serial_stream(fz_rig_t *rig, const uint8_t *data, size_t size, int fix_checksums);
/* The CAN counterpart: 12-byte records [tag][id lo][id hi][dlc][8 data]; tag bit 0: a sample
 * (data as 3 x int16 acceleration and int16 temperature, temperature step = id hi, reps = dlc);
 * else a frame to the node (tag bit 1 clear: to 0x600 + node, set: to the raw 11-bit id; tag bit 2
 * on a CAL_COMMIT: its CRC replaced by the one of the fields staged, so fuzzed values get stored). */
#define FZ_CAN_RECORD 12u
void fz_run_can_stream(fz_rig_t *rig, const uint8_t *data, size_t size);

/* Copy a line (no '\n') into out; a `$SFTC,<t_ref>,<t_lo>,<t_hi>,<crc>*HH` gets the CRC of its three
 * temperatures and the cubic coefficients b has staged ($SFTW), so fuzzed cubic models get stored.
 * Returns the length written (at most cap). */
size_t fz_rewrite_sftc(const fw_board_t *b, const uint8_t *line, size_t len, uint8_t *out, size_t cap);
/* Rewrite the `HH` after the last '*' of a line (no '\n') to the XOR checksum of the body between
 * the last '$' before it and the '*', so mutated commands still reach the parser. */
void fz_fix_line_checksum(uint8_t *line, size_t len);

/* --- invariants ------------------------------------------------------------------------------- */

/* The float fields of fw_cal_t and fw_cubic_t (the coefficients applied: b->cal, b->cubic), listed
 * by hand; fuzz_common.c refuses to compile when either struct's size changes, so a new coefficient
 * array cannot be left out of the check silently. */
typedef struct fz_float_field { const char *name; size_t offset; uint32_t count; } fz_float_field_t;
extern const fz_float_field_t fz_cal_floats[];
extern const uint32_t fz_cal_n_fields;
extern const fz_float_field_t fz_cubic_floats[];
extern const uint32_t fz_cubic_n_fields;
/* Number of non-finite floats in c; *where (may be NULL) names the first one. Pure: no abort. */
uint32_t fz_cal_nonfinite(const fw_cal_t *c, char *where, size_t where_cap);
uint32_t fz_cubic_nonfinite(const fw_cubic_t *c, char *where, size_t where_cap);
/* 0 when a slot image the core asked to program decodes VALID with finite coefficients, else -1 and
 * why in *why. Pure: no abort. */
int fz_written_image_ok(const uint8_t img[FW_NVM_SLOT_BYTES], char *why, size_t why_cap);
/* 0 when out[0..len) is exactly one `$BODY*HH\n` frame fw_unframe accepts. Pure. */
int fz_serial_frame_ok(const uint8_t *out, uint32_t len);

/* Abort on a violation of the board's invariants (the list at the top). */
void fz_check_board(const fz_rig_t *rig, const char *after);
/* Print `FW_FUZZ INVARIANT VIOLATION: ...` and abort (libFuzzer saves the input). */
void fz_violation(const char *what, const char *detail, const char *after);

/* --- independent codecs (the harness does not trust the core's) ------------------------------- */
uint32_t fz_crc32(const uint8_t *p, size_t n);       /* zlib CRC-32, bitwise */
uint32_t fz_get_u32(const uint8_t *p);
void fz_put_u32(uint8_t *p, uint32_t v);
/* Recompute the value CRCs and the record CRC of a record image by its own version field (v1: the
 * layout of fw_nvm.h; other versions: the record CRC at length - 4), so fuzzed coefficients reach
 * the decoder's value checks instead of dying at a CRC. Leaves images with no plausible header. */
void fz_fix_record_crcs(uint8_t img[FW_NVM_SLOT_BYTES]);

#endif
