/* flash_nvm.h: the two NVM record slots in STM32F4 flash sectors 2 and 3 (16 KB each). */
#ifndef FLASH_NVM_H
#define FLASH_NVM_H

#include <stdint.h>

#define FLASH_NVM_OK          0
#define FLASH_NVM_ERR_ARG     (-1)
#define FLASH_NVM_ERR_FLASH   (-2)   /* the controller flagged an error (SR OPERR/WRPERR/PG*ERR) */
#define FLASH_NVM_ERR_TIMEOUT (-3)   /* BSY did not clear in time */
#define FLASH_NVM_ERR_SUPPLY  (-4)   /* VDD below the PVD's 2.7 V: no erase started */
#define FLASH_NVM_ERR_VERIFY  (-5)   /* read back differs */

#define FLASH_NVM_ERASE_TIMEOUT_US 1000000u   /* 16 KB sector, x32: 250 ms typ., 500 ms max (DS8626) */
#define FLASH_NVM_WORD_TIMEOUT_US  1000u      /* one word, x32: 16 us typ., 100 us max */

/* The microsecond clock the waits are bounded with (TIM2) and a hook called before the erase (the
 * target feeds its watchdog there: an erase stalls the CPU for up to 500 ms). */
void flash_nvm_init(uint32_t (*clock_us)(void), void (*before_erase)(void));
int flash_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len);
/* Check the supply (PVD), erase the slot's sector, program len bytes by 32-bit words, verify.
 * FLASH_NVM_OK or one of the errors above (flash_nvm_error_text says it in words). */
int flash_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len);
const char *flash_nvm_error_text(int rc);

#endif
