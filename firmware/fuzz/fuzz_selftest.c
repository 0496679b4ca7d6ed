/* fuzz_selftest.c: the invariant checks themselves must be able to fail (no libFuzzer main).
 *
 * Why: a check that never fires passes every fuzz run. This puts a NaN and an infinity into every
 * coefficient of fw_cal_t and fw_cubic_t that fz_cal_floats / fz_cubic_floats list and expects each to
 * be named; checks that the listed floats and the known integer fields account for each whole struct
 * (a float array added but not listed fails here as well as the size check); and feeds the
 * written-image and serial-frame checks images and frames they must refuse. Prints `SELFTEST OK`
 * and exits 0, or names the first check that failed to fire and exits 1. */
#include <math.h>
#include <stdio.h>
#include <string.h>
#include "fuzz_common.h"

static int failures;

static void expect(int cond, const char *what)
{
    if (!cond) { printf("SELFTEST FAIL: %s\n", what); failures++; }
}

/* NaN, +inf, -inf into each listed float of obj in turn: counted once and named each time. */
static uint32_t poison_each(void *obj, size_t size, const fz_float_field_t *fields, uint32_t n_fields, const char *prefix,
                            uint32_t (*count)(const void *, char *, size_t), void (*reset)(void *))
{
    static const float BAD[3] = { NAN, INFINITY, -INFINITY };
    uint32_t total = 0;
    for (uint32_t f = 0; f < n_fields; f++) {
        for (uint32_t i = 0; i < fields[f].count; i++, total++) {
            for (uint32_t k = 0; k < 3u; k++) {
                char where[96] = "";
                char want[64];
                reset(obj);
                memcpy((uint8_t *)obj + fields[f].offset + i * sizeof(float), &BAD[k], sizeof(float));
                uint32_t n = count(obj, where, sizeof where);
                snprintf(want, sizeof want, "%s%s[%u]", prefix, fields[f].name, (unsigned)i);
                expect(n == 1u, "a non-finite coefficient is counted once");
                expect(strncmp(where, want, strlen(want)) == 0, "the non-finite coefficient is named");
            }
        }
    }
    reset(obj);
    expect(count(obj, NULL, 0) == 0u, "no non-finite coefficient in a clean struct");
    (void)size;
    return total;
}

static uint32_t cal_count(const void *o, char *w, size_t n) { return fz_cal_nonfinite(o, w, n); }
static uint32_t cubic_count(const void *o, char *w, size_t n) { return fz_cubic_nonfinite(o, w, n); }
static void cal_reset(void *o) { fw_cal_zero(o); }
static void cubic_reset(void *o) { memset(o, 0, sizeof(fw_cubic_t)); }

static void check_every_float(void)
{
    fw_cal_t cal;
    fw_cubic_t cubic;
    uint32_t n_cal = poison_each(&cal, sizeof cal, fz_cal_floats, fz_cal_n_fields, "", cal_count, cal_reset);
    uint32_t n_cubic = poison_each(&cubic, sizeof cubic, fz_cubic_floats, fz_cubic_n_fields, "cubic.", cubic_count,
                                   cubic_reset);
    /* the listed floats plus the known integer fields account for the whole struct but its padding */
    expect((size_t)n_cal * 4u + 2u * 4u + 2u + 2u == sizeof(fw_cal_t), "fz_cal_floats lists every float of fw_cal_t");
    expect((size_t)n_cubic * 4u + 4u + 1u + 3u == sizeof(fw_cubic_t), "fz_cubic_floats lists every float of fw_cubic_t");
    expect(n_cal == 18u && n_cubic == 51u, "18 version-1 and 51 version-2 coefficients");
    printf("coefficients checked: fw_cal_t %u floats (%zu bytes), fw_cubic_t %u floats (%zu bytes)\n", (unsigned)n_cal,
           sizeof(fw_cal_t), (unsigned)n_cubic, sizeof(fw_cubic_t));
}

static void check_written_image(void)
{
    uint8_t img[FW_NVM_SLOT_BYTES];
    char why[160];
    fw_cal_t c;
    fw_cal_zero(&c);
    c.thermal[0] = 0.5f;
    c.thermal_crc = fw_crc32_f32(c.thermal, 6);
    c.comp = 1;
    memset(img, 0xFF, sizeof img);
    fw_nvm_encode(&c, 3, img);
    expect(fz_written_image_ok(img, why, sizeof why) == 0, "a good record passes the written-image check");
    img[20] ^= 1u;   /* a coefficient byte: value CRC and record CRC now wrong */
    expect(fz_written_image_ok(img, why, sizeof why) != 0, "a record with a bad CRC is refused");
    img[20] ^= 1u;
    float nan = NAN;
    memcpy(img + 16, &nan, 4);   /* thermal[1] = NaN with every CRC recomputed: decodes VALID */
    fz_fix_record_crcs(img);
    expect(fz_written_image_ok(img, why, sizeof why) != 0, "a valid-CRC record holding a NaN is refused");
    memset(img, 0xFF, sizeof img);
    expect(fz_written_image_ok(img, why, sizeof why) != 0, "an erased image is not a written record");
    /* version 2: a good cubic record passes, one with a NaN cubic coefficient (CRCs fixed) does not */
    fw_cubic_t cu;
    memset(&cu, 0, sizeof cu);
    cu.t_ref_c = 25.0f;
    cu.t_lo_c = -10.0f;
    cu.t_hi_c = 60.0f;
    cu.c[0][0] = cu.c[0][4] = cu.c[0][8] = 1.0f;
    cu.crc = fw_cubic_crc(&cu);
    cu.present = 1;
    memset(img, 0xFF, sizeof img);
    expect(fw_nvm_encode_rec(&c, &cu, 4, img) == FW_NVM_RECORD2_BYTES, "a cubic record is version 2");
    expect(fz_written_image_ok(img, why, sizeof why) == 0, "a good version-2 record passes");
    memcpy(img + 112 + 48 * 3 + 4 * 5, &nan, 4);   /* c[3][5] */
    fz_fix_record_crcs(img);
    expect(fz_written_image_ok(img, why, sizeof why) != 0, "a valid-CRC version-2 record holding a NaN is refused");
}

static void check_frames(void)
{
    uint8_t good[16] = "$A,START*00\n";
    fz_fix_line_checksum(good, 11);
    expect(fz_serial_frame_ok(good, 12) == 0, "a frame with the right checksum passes");
    uint8_t bad[16];
    memcpy(bad, good, 12);
    bad[9] = bad[9] == '0' ? '1' : '0';
    expect(fz_serial_frame_ok(bad, 12) != 0, "a frame with a wrong checksum is refused");
    expect(fz_serial_frame_ok(good, 11) != 0, "a frame without its newline is refused");
    uint8_t two[24] = "$I,SIM$1,X*00\n";   /* a '$' inside the body: the station starts a new frame there */
    fz_fix_line_checksum(two, 13);
    expect(fz_serial_frame_ok(two, 14) != 0, "a body holding '$' is refused");
}

/* The structure-aware helpers do what fuzz_common.h says: a $SFTC with a wrong CRC, rewritten, stores
 * the staged cubic model; a mutated NVM record with its CRCs recomputed boots. */
static void check_fixups(void)
{
    static fz_rig_t rig;
    fw_identity_t id;
    memset(&rig, 0, sizeof rig);
    fz_nvm_preset(&rig.nvm, 1);
    fz_identity(0, &id);
    fz_boot(&rig, &id, 0, 1);
    fz_command(&rig, "SFTW,0,1,0,0,0,1,0,0,0,1,0.01,0,0");
    fz_command(&rig, "SFTW,1,1e-5,0,0,0,0,0,0,0,0,0,0,0");
    fz_command(&rig, "SFTW,2,0,0,0,0,0,0,0,0,0,0,0,0");
    fz_command(&rig, "SFTW,3,0,0,0,0,0,0,0,0,-0,0,0,1e-9");
    static const char SFTC[] = "$SFTC,25,-10,60,00000000*00\n";
    fz_run_serial_stream(&rig, (const uint8_t *)SFTC, sizeof SFTC - 1u, 1);
    expect(rig.board.cubic.present == 1u && rig.board.cubic.c[1][0] == 1e-5f, "a rewritten $SFTC stores the staged model");
    uint8_t img[FW_NVM_SLOT_BYTES];
    memcpy(img, rig.nvm.slot[rig.board.nvm_slot == 1 ? 1 : 0], sizeof img);
    float v = 123.5f;
    memcpy(img + 112, &v, 4);   /* c[0][0] */
    fw_cubic_t cu;
    expect(fw_nvm_decode_rec(img, sizeof img, NULL, &cu, NULL) == FW_SLOT_CORRUPT, "a mutated record is CORRUPT");
    fz_fix_record_crcs(img);
    expect(fw_nvm_decode_rec(img, sizeof img, NULL, &cu, NULL) == FW_SLOT_VALID && cu.c[0][0] == 123.5f,
           "fz_fix_record_crcs makes it VALID with the mutated value");
}

int main(void)
{
    check_every_float();
    check_written_image();
    check_frames();
    check_fixups();
    if (failures) return 1;
    printf("SELFTEST OK\n");
    return 0;
}
