/* semihost.h: ARM semihosting (BKPT 0xAB on M-profile) for the QEMU target: the NVM file and the
 * bench's report. QEMU must run with `-semihosting-config enable=on,target=native`, otherwise the
 * BKPT is a debug event with no debugger and the core locks up. */
#ifndef SEMIHOST_H
#define SEMIHOST_H

#include <stdint.h>

#define SH_SYS_OPEN   0x01
#define SH_SYS_CLOSE  0x02
#define SH_SYS_WRITE0 0x04
#define SH_SYS_WRITE  0x05
#define SH_SYS_READ   0x06
#define SH_SYS_SEEK   0x0A
#define SH_SYS_FLEN   0x0C
#define SH_SYS_EXIT   0x18

/* fopen() modes of SYS_OPEN */
#define SH_MODE_RB    1
#define SH_MODE_RPB   3   /* "r+b": read/write, must exist */
#define SH_MODE_WPB   7   /* "w+b": create/truncate */

int32_t sh_call(int32_t op, void *arg);
int32_t sh_open(const char *path, int32_t mode);
int32_t sh_close(int32_t fd);
/* Returns the number of bytes NOT transferred (semihosting convention), -1 on error. */
int32_t sh_read(int32_t fd, void *buf, uint32_t len);
int32_t sh_write(int32_t fd, const void *buf, uint32_t len);
int32_t sh_seek(int32_t fd, uint32_t pos);
int32_t sh_flen(int32_t fd);
void sh_puts(const char *s);                   /* SYS_WRITE0 to QEMU's stderr/console */
__attribute__((noreturn)) void sh_exit(int ok);

/* NVM on the host file `nvm.bin` (QEMU's working directory): slot k at offset k * slot_bytes;
 * a missing file or a short file reads erased (0xFF). */
int sh_nvm_read(uint32_t slot, uint8_t *buf, uint32_t len);
int sh_nvm_write(uint32_t slot, const uint8_t *buf, uint32_t len);

#endif
