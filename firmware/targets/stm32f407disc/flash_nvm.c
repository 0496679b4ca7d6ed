/* flash_nvm.c: NVM slots on the STM32F4 flash controller (RM0090 section 3.6).
 *
 * Slot 0 = sector 2 (0x08008000), slot 1 = sector 3 (0x0800C000); the linker script keeps code out
 * of both. Write = supply check (PVD at 2.7 V: PSIZE x32 needs 2.7-3.6 V, and a supply that sags
 * during an erase leaves a half-erased sector), unlock (KEYR KEY1, KEY2), sector erase (SER, SNB,
 * STRT, wait BSY), program by word (PG, PSIZE x32, wait BSY after every word), lock, then read back
 * and compare. Every BSY wait is bounded by the microsecond clock; a controller that never finishes
 * is an error the core reports (`E,CALW,flash write failed`, the target adds `E,NVM,<why>`), never a
 * hang. The core writes the two slots alternately (A/B), so a reset during an erase loses at most
 * the record being written. Code runs from flash, so the CPU stalls while the controller erases
 * (16 KB: ~250 ms typical); the station waits for the `A,CALW` reply, so no byte arrives meanwhile. */
#include <string.h>
#include "stm32f4_regs.h"
#include "flash_nvm.h"
#include "fw_hal.h"

extern const uint8_t _nvm_slot0[], _nvm_slot1[];   /* from the linker script */

static uint32_t (*g_clock_us)(void);
static void (*g_before_erase)(void);

void flash_nvm_init(uint32_t (*clock_us)(void), void (*before_erase)(void))
{
    g_clock_us = clock_us;
    g_before_erase = before_erase;
}

static const uint8_t *slot_addr(uint32_t slot)
{
    return slot == 0u ? _nvm_slot0 : _nvm_slot1;
}

static int wait_idle(uint32_t timeout_us)
{
    uint32_t sr, t0 = g_clock_us ? g_clock_us() : 0u, spins = 0;
    while ((sr = FLASH_SR) & FLASH_SR_BSY) {
        /* without a clock (never in this firmware) a spin count at <= 168 MHz bounds it instead */
        if (g_clock_us ? g_clock_us() - t0 > timeout_us : ++spins > timeout_us * 168u) {
            return FLASH_NVM_ERR_TIMEOUT;
        }
    }
    return (sr & FLASH_SR_ERRORS) ? FLASH_NVM_ERR_FLASH : FLASH_NVM_OK;
}

const char *flash_nvm_error_text(int rc)
{
    switch (rc) {
    case FLASH_NVM_ERR_ARG: return "bad slot";
    case FLASH_NVM_ERR_FLASH: return "flash controller error";
    case FLASH_NVM_ERR_TIMEOUT: return "flash timeout";
    case FLASH_NVM_ERR_SUPPLY: return "supply below 2.7 V: not erased";
    case FLASH_NVM_ERR_VERIFY: return "flash verify mismatch";
    default: return "ok";
    }
}

int flash_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len)
{
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return FLASH_NVM_ERR_ARG;
    }
    memcpy(buf, slot_addr(slot), len);   /* an erased sector reads 0xFF */
    return FLASH_NVM_OK;
}

int flash_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len)
{
    volatile uint32_t *dst;
    uint32_t i, word;
    int rc;

    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return FLASH_NVM_ERR_ARG;
    }
    if (PWR_CSR & PWR_CSR_PVDO) {
        return FLASH_NVM_ERR_SUPPLY;          /* the PVD (enabled at boot) says VDD < 2.7 V */
    }
    dst = (volatile uint32_t *)(uintptr_t)slot_addr(slot);

    rc = wait_idle(FLASH_NVM_ERASE_TIMEOUT_US);
    if (rc == FLASH_NVM_ERR_TIMEOUT) {
        return rc;                            /* still busy from something else: touch nothing */
    }
    if (FLASH_CR & FLASH_CR_LOCK) {
        FLASH_KEYR = FLASH_KEY1;
        FLASH_KEYR = FLASH_KEY2;
    }
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;   /* clear stale flags (write 1) */

    /* sector erase: sector 2 + slot, 32-bit parallelism (2.7-3.6 V) */
    if (g_before_erase) {
        g_before_erase();
    }
    FLASH_CR = FLASH_CR_PSIZE_X32 | FLASH_CR_SER | FLASH_CR_SNB(2u + slot);
    FLASH_CR |= FLASH_CR_STRT;
    rc = wait_idle(FLASH_NVM_ERASE_TIMEOUT_US);
    FLASH_CR &= ~(FLASH_CR_SER | FLASH_CR_SNB(0xFu));

    /* program by word; the tail of a non-multiple-of-4 length is padded with 0xFF (erased) */
    if (rc == FLASH_NVM_OK) {
        FLASH_CR = FLASH_CR_PSIZE_X32 | FLASH_CR_PG;
        for (i = 0; i < len && rc == FLASH_NVM_OK; i += 4u) {
            word = 0xFFFFFFFFu;
            memcpy(&word, buf + i, (len - i) < 4u ? (len - i) : 4u);
            dst[i / 4u] = word;
            __asm volatile("dsb" ::: "memory");
            rc = wait_idle(FLASH_NVM_WORD_TIMEOUT_US);
        }
        FLASH_CR &= ~FLASH_CR_PG;
    }
    FLASH_CR |= FLASH_CR_LOCK;

    /* the data cache may hold the sector's old lines: reset it (only allowed while disabled) */
    FLASH_ACR &= ~FLASH_ACR_DCEN;
    FLASH_ACR |= FLASH_ACR_DCRST;
    FLASH_ACR &= ~FLASH_ACR_DCRST;
    FLASH_ACR |= FLASH_ACR_DCEN;

    if (rc == FLASH_NVM_OK && memcmp((const void *)(uintptr_t)dst, buf, len) != 0) {
        rc = FLASH_NVM_ERR_VERIFY;
    }
    return rc;
}
