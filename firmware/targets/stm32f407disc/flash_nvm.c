/* flash_nvm.c: NVM slots on the STM32F4 flash controller (RM0090 section 3.6).
 *
 * Slot 0 = sector 2 (0x08008000), slot 1 = sector 3 (0x0800C000); the linker script keeps code out
 * of both. Write = unlock (KEYR KEY1, KEY2), sector erase (SER, SNB, STRT, wait BSY), program by
 * word (PG, PSIZE x32, wait BSY after every word), lock, then read back and compare. The core writes
 * the two slots alternately (A/B), so a reset during an erase loses at most the record being written.
 * Code runs from flash, so the CPU stalls while the controller erases (16 KB: ~250 ms typical) or
 * programs; the station waits for the `A,CALW` reply, so no byte arrives meanwhile. */
#include <string.h>
#include "stm32f4_regs.h"
#include "flash_nvm.h"
#include "fw_hal.h"

extern const uint8_t _nvm_slot0[], _nvm_slot1[];   /* from the linker script */

static const uint8_t *slot_addr(uint32_t slot)
{
    return slot == 0u ? _nvm_slot0 : _nvm_slot1;
}

static int wait_idle(void)
{
    uint32_t sr;
    while ((sr = FLASH_SR) & FLASH_SR_BSY) {
    }
    return (sr & FLASH_SR_ERRORS) ? -1 : 0;
}

int flash_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len)
{
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    memcpy(buf, slot_addr(slot), len);   /* an erased sector reads 0xFF */
    return 0;
}

int flash_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len)
{
    volatile uint32_t *dst;
    uint32_t i, word;
    int rc;

    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    dst = (volatile uint32_t *)(uintptr_t)slot_addr(slot);

    if (wait_idle() != 0) {
        FLASH_SR = FLASH_SR_ERRORS;           /* clear stale error flags (write 1) */
    }
    if (FLASH_CR & FLASH_CR_LOCK) {
        FLASH_KEYR = FLASH_KEY1;
        FLASH_KEYR = FLASH_KEY2;
    }
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;

    /* sector erase: sector 2 + slot, 32-bit parallelism (2.7-3.6 V) */
    FLASH_CR = FLASH_CR_PSIZE_X32 | FLASH_CR_SER | FLASH_CR_SNB(2u + slot);
    FLASH_CR |= FLASH_CR_STRT;
    rc = wait_idle();
    FLASH_CR &= ~(FLASH_CR_SER | FLASH_CR_SNB(0xFu));

    /* program by word; the tail of a non-multiple-of-4 length is padded with 0xFF (erased) */
    if (rc == 0) {
        FLASH_CR = FLASH_CR_PSIZE_X32 | FLASH_CR_PG;
        for (i = 0; i < len && rc == 0; i += 4u) {
            word = 0xFFFFFFFFu;
            memcpy(&word, buf + i, (len - i) < 4u ? (len - i) : 4u);
            dst[i / 4u] = word;
            __asm volatile("dsb" ::: "memory");
            rc = wait_idle();
        }
        FLASH_CR &= ~FLASH_CR_PG;
    }
    FLASH_CR |= FLASH_CR_LOCK;

    /* the data cache may hold the sector's old lines: reset it (only allowed while disabled) */
    FLASH_ACR &= ~FLASH_ACR_DCEN;
    FLASH_ACR |= FLASH_ACR_DCRST;
    FLASH_ACR &= ~FLASH_ACR_DCRST;
    FLASH_ACR |= FLASH_ACR_DCEN;

    if (rc == 0 && memcmp((const void *)(uintptr_t)dst, buf, len) != 0) {
        rc = -1;
    }
    return rc;
}
