/* host.h: the Linux host target (one process per board), shared between its files. */
#ifndef FW_HOST_H
#define FW_HOST_H

#include <stdint.h>
#include "fw_board.h"

typedef struct host_nvm {
    int fd;
    long tear_after;        /* >= 0: the next write programs only this many bytes, then exit */
} host_nvm_t;

int host_nvm_open(host_nvm_t *n, const char *path);   /* creates an erased (0xFF) file if absent */
int host_nvm_read(void *ctx, uint32_t slot, uint8_t *buf, uint32_t len);
int host_nvm_write(void *ctx, uint32_t slot, const uint8_t *buf, uint32_t len);

/* The station link: non-blocking fd with an output queue (dropped beyond its size, like a full
 * USB buffer), serial frames or slcan lines. */
typedef struct host_link {
    int fd;
    int hup;                /* the other side is gone (pty slave closed): retry later */
    uint32_t out_len;
    uint64_t bytes_dropped;
    uint8_t in_line[64];    /* slcan receive line */
    uint32_t in_len;
} host_link_t;

void host_link_write(host_link_t *l, const uint8_t *buf, uint32_t len);
void host_link_flush(host_link_t *l);
int host_link_pending(const host_link_t *l);
void host_uart_write(void *ctx, const uint8_t *buf, uint32_t len);
void host_can_send(void *ctx, uint16_t id, uint8_t dlc, const uint8_t *data);
/* The hal's single context pointer: everything the callbacks reach. */
typedef struct host_ctx {
    host_link_t link;
    host_nvm_t nvm;
} host_ctx_t;

/* slcan receive: bytes in, fw_can_rx for each well-formed `t` line. */
void host_slcan_rx(host_link_t *l, fw_board_t *b, const uint8_t *data, uint32_t len);

#endif
