/* fw_hal.h: what the portable core needs from a board (CONTRACT between core and targets).
 *
 * The core never touches a register, a file or a socket: each target (host process, QEMU
 * netduinoplus2, STM32F407 Discovery) fills one fw_hal_t with its own functions, in the style of
 * ST's platform-independent MEMS drivers (a context pointer plus read/write functions). No heap
 * anywhere: every buffer is a fixed array inside fw_board_t.
 */
#ifndef FW_HAL_H
#define FW_HAL_H

#include <stdint.h>

#define FW_NVM_SLOTS 2u          /* two record slots (A/B): a torn write never destroys the last good one */
/* Bytes per slot. 512 since issue 42 (was 256): a version-2 record (fw_nvm.h, the cubic SFEM) is
 * 312 bytes. What it means for the targets:
 *  - host: the --nvm file is 2 x 512 = 1024 bytes (host_nvm_open pads a shorter file with 0xFF);
 *  - QEMU: nvm.bin is 1024 bytes, slot k at [512 k, 512 k + 512) (semihost.c scales with this
 *    constant; targets/qemu/README.md still says 256);
 *  - Discovery: each slot is still one 16 KB flash sector (2 and 3), so nothing moves; a write
 *    programs at most 312 bytes (78 words, a multiple of 4) and reads back 512;
 *  - a 512-byte file of older firmware reads as slot 0 = its old slots 0 and 1 back to back (the
 *    old slot 0 record stays valid, the old slot 1 record is not seen) and slot 1 erased.
 * Every nvm_read asks for FW_NVM_SLOT_BYTES (the erased check covers the whole slot); nvm_write
 * gets the record length (104 or 312) and must leave the rest of the slot erased. */
#define FW_NVM_SLOT_BYTES 512u

typedef struct fw_hal {
    void *ctx;
    /* Station link, serial boards: write len bytes (whole frames). NULL on a CAN board. */
    void (*uart_write)(void *ctx, const uint8_t *buf, uint32_t len);
    /* Station link, CAN boards: send one CAN 2.0A frame. NULL on a serial board. */
    void (*can_send)(void *ctx, uint16_t id, uint8_t dlc, const uint8_t *data);
    /* Non-volatile memory, one slot of FW_NVM_SLOT_BYTES: read the slot (an erased slot reads
     * 0xFF), erase-and-program it. Return 0 on success, nonzero on a failed flash operation. */
    int (*nvm_read)(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len);
    int (*nvm_write)(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len);
} fw_hal_t;

/* One sensor sample as the sensor driver (or the sensor bridge) delivers it at data-ready. */
typedef struct fw_raw_sample {
    uint32_t t_us;     /* board clock at data-ready, microseconds since power-up (wraps) */
    int32_t acc[3];    /* raw counts x y z */
    int32_t temp;      /* raw temperature count */
} fw_raw_sample_t;

#endif
