/* semihost.c: ARM semihosting calls and the nvm.bin slots (see semihost.h). */
#include <string.h>
#include "semihost.h"
#include "fw_hal.h"

#define NVM_FILE "nvm.bin"
#define NVM_FILE_BYTES (FW_NVM_SLOTS * FW_NVM_SLOT_BYTES)

int32_t sh_call(int32_t op, void *arg)
{
    register int32_t r0 __asm("r0") = op;
    register void *r1 __asm("r1") = arg;
    __asm volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

int32_t sh_open(const char *path, int32_t mode)
{
    uint32_t a[3] = {(uint32_t)(uintptr_t)path, (uint32_t)mode, (uint32_t)strlen(path)};
    return sh_call(SH_SYS_OPEN, a);
}

int32_t sh_close(int32_t fd)
{
    uint32_t a[1] = {(uint32_t)fd};
    return sh_call(SH_SYS_CLOSE, a);
}

int32_t sh_read(int32_t fd, void *buf, uint32_t len)
{
    uint32_t a[3] = {(uint32_t)fd, (uint32_t)(uintptr_t)buf, len};
    return sh_call(SH_SYS_READ, a);
}

int32_t sh_write(int32_t fd, const void *buf, uint32_t len)
{
    uint32_t a[3] = {(uint32_t)fd, (uint32_t)(uintptr_t)buf, len};
    return sh_call(SH_SYS_WRITE, a);
}

int32_t sh_seek(int32_t fd, uint32_t pos)
{
    uint32_t a[2] = {(uint32_t)fd, pos};
    return sh_call(SH_SYS_SEEK, a);
}

int32_t sh_flen(int32_t fd)
{
    uint32_t a[1] = {(uint32_t)fd};
    return sh_call(SH_SYS_FLEN, a);
}

void sh_puts(const char *s)
{
    (void)sh_call(SH_SYS_WRITE0, (void *)(uintptr_t)s);
}

void sh_exit(int ok)
{
    /* AArch32 SYS_EXIT takes the reason in r1 itself (not a block): QEMU exits with status 0 for
     * ADP_Stopped_ApplicationExit (0x20026), 1 for anything else (ADP_Stopped_RunTimeErrorUnknown). */
    (void)sh_call(SH_SYS_EXIT, (void *)(uintptr_t)(ok ? 0x20026u : 0x20023u));
    for (;;) {
    }
}

int sh_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len)
{
    int32_t fd, flen, left;
    uint32_t off = slot * FW_NVM_SLOT_BYTES, got = 0;

    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    memset(buf, 0xFF, len);
    fd = sh_open(NVM_FILE, SH_MODE_RB);
    if (fd < 0) {
        return 0;   /* no file yet: an erased part */
    }
    flen = sh_flen(fd);
    if (flen > (int32_t)off) {
        uint32_t want = (uint32_t)flen - off < len ? (uint32_t)flen - off : len;
        if (sh_seek(fd, off) == 0) {
            left = sh_read(fd, buf, want);
            if (left >= 0 && (uint32_t)left <= want) {
                got = want - (uint32_t)left;
            }
        }
        if (got < len) {
            memset(buf + got, 0xFF, len - got);
        }
    }
    (void)sh_close(fd);
    return 0;
}

int sh_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len)
{
    static const uint8_t erased[32] = {
        0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF,
        0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF};
    int32_t fd, flen;
    uint32_t pos, off = slot * FW_NVM_SLOT_BYTES;
    int rc = 0;

    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) {
        return -1;
    }
    fd = sh_open(NVM_FILE, SH_MODE_RPB);
    if (fd < 0) {
        fd = sh_open(NVM_FILE, SH_MODE_WPB);
    }
    if (fd < 0) {
        return -1;
    }
    /* Extend a new or short file with erased bytes first, so the other slot never reads zeros. */
    flen = sh_flen(fd);
    pos = flen > 0 ? (uint32_t)flen : 0u;
    if (pos < NVM_FILE_BYTES && sh_seek(fd, pos) == 0) {
        while (pos < NVM_FILE_BYTES && rc == 0) {
            uint32_t n = NVM_FILE_BYTES - pos < sizeof erased ? NVM_FILE_BYTES - pos : (uint32_t)sizeof erased;
            rc = sh_write(fd, erased, n) == 0 ? 0 : -1;
            pos += n;
        }
    }
    /* "erase and program" the whole slot: data then erased filler */
    if (rc == 0 && sh_seek(fd, off) != 0) {
        rc = -1;
    }
    if (rc == 0 && sh_write(fd, buf, len) != 0) {
        rc = -1;
    }
    for (pos = len; rc == 0 && pos < FW_NVM_SLOT_BYTES;) {
        uint32_t n = FW_NVM_SLOT_BYTES - pos < sizeof erased ? FW_NVM_SLOT_BYTES - pos : (uint32_t)sizeof erased;
        rc = sh_write(fd, erased, n) == 0 ? 0 : -1;
        pos += n;
    }
    if (sh_close(fd) != 0) {
        rc = -1;
    }
    return rc;
}
