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
#define FW_NVM_SLOT_BYTES 256u   /* bytes per slot, enough for fw_nvm_record_t */

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
