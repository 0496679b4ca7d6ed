/* flash_nvm.h: the two NVM record slots in STM32F4 flash sectors 2 and 3 (16 KB each). */
#ifndef FLASH_NVM_H
#define FLASH_NVM_H

#include <stdint.h>

int flash_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len);
/* Erase the slot's sector, program len bytes by 32-bit words, verify. 0 or -1. */
int flash_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len);

#endif
