/* host_nvm.c: the board's flash as a file of FW_NVM_SLOTS slots (erased bytes read 0xFF).
 * A write erases the slot and programs it (one pwrite of the whole slot image), then fsync. */
#include <errno.h>
#include <fcntl.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include "host.h"

int host_nvm_open(host_nvm_t *n, const char *path)
{
    uint8_t ff[FW_NVM_SLOTS * FW_NVM_SLOT_BYTES];
    struct stat st;
    n->fd = open(path, O_RDWR | O_CREAT, 0644);
    if (n->fd < 0 || fstat(n->fd, &st) != 0) return -1;
    if (st.st_size < (off_t)sizeof ff) {   /* new (or short) file: erased flash */
        memset(ff, 0xFF, sizeof ff);
        size_t have = (size_t)st.st_size;
        if (pwrite(n->fd, ff + have, sizeof ff - have, (off_t)have) != (ssize_t)(sizeof ff - have)) return -1;
        if (fsync(n->fd) != 0) return -1;
    }
    return 0;
}

int host_nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len)
{
    host_nvm_t *n = &((host_ctx_t *)ctx)->nvm;
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) return -1;
    ssize_t r = pread(n->fd, buf, len, (off_t)slot * FW_NVM_SLOT_BYTES);
    return r == (ssize_t)len ? 0 : -1;
}

int host_nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len)
{
    host_nvm_t *n = &((host_ctx_t *)ctx)->nvm;
    uint8_t img[FW_NVM_SLOT_BYTES];
    if (slot >= FW_NVM_SLOTS || len > FW_NVM_SLOT_BYTES) return -1;
    memset(img, 0xFF, sizeof img);
    uint32_t prog = len;
    if (n->tear_after >= 0 && (unsigned long)n->tear_after < prog) prog = (uint32_t)n->tear_after;
    memcpy(img, buf, prog);
    ssize_t w = pwrite(n->fd, img, sizeof img, (off_t)slot * FW_NVM_SLOT_BYTES);
    int ok = w == (ssize_t)sizeof img && fsync(n->fd) == 0;
    if (n->tear_after >= 0) _exit(75);   /* power lost in the middle of programming */
    return ok ? 0 : -1;
}
