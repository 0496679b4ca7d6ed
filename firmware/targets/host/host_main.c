/* host_main.c: build/host/fwboard, the board firmware as a Linux process (one per board).
 *
 *   fwboard (--uart-fd N | --uart-pty) --bridge-fd N --nvm PATH [--can NODE] [--fw VERSION]
 *           [--nvm-tear-after BYTES]
 *
 * The station link is fd N (e.g. the master of a pty the parent made) or a pty made here (its
 * slave path printed as `PTY <path>` on stdout). Serial boards speak design 3.1 on it; with --can
 * it carries CAN frames as slcan lines `t<id><dlc><data>\r` both ways. The sensor bridge (fd N)
 * brings the identity strap and the samples (core/fw_bridge.h). poll() only, no busy loop; exits
 * on EOF of the bridge or SIGTERM.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>
#include "fw_bridge.h"
#include "host.h"

static volatile sig_atomic_t stop_requested;
static double hup_since;

static double now_s(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}
static void on_term(int sig) { (void)sig; stop_requested = 1; }

static fw_board_t board;
static host_ctx_t host;

static void usage(void)
{
    fprintf(stderr, "usage: fwboard (--uart-fd N | --uart-pty) --bridge-fd N --nvm PATH [--can NODE] "
                    "[--fw VERSION] [--nvm-tear-after BYTES]\n");
    exit(2);
}

static void make_raw(int fd)
{
    struct termios tio;
    if (isatty(fd) && tcgetattr(fd, &tio) == 0) {
        cfmakeraw(&tio);
        tcsetattr(fd, TCSANOW, &tio);
    }
}

static int open_own_pty(void)
{
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) != 0 || unlockpt(m) != 0) return -1;
    const char *path = ptsname(m);
    if (!path) return -1;
    int s = open(path, O_RDWR | O_NOCTTY);   /* kept open: no hang-up while no station is attached */
    if (s < 0) return -1;
    make_raw(s);
    printf("PTY %s\n", path);
    fflush(stdout);
    return m;
}

static void write_all(int fd, const uint8_t *p, uint32_t n)
{
    while (n) {
        ssize_t w = write(fd, p, n);
        if (w > 0) { p += w; n -= (uint32_t)w; }
        else if (w < 0 && (errno == EINTR || errno == EAGAIN)) { struct pollfd q = { fd, POLLOUT, 0 }; poll(&q, 1, 100); }
        else return;
    }
}

int main(int argc, char **argv)
{
    int uart_fd = -1, bridge_fd = -1, own_pty = 0, can_node = 0;
    const char *nvm_path = NULL, *fw = NULL;
    host.nvm.tear_after = -1;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--uart-pty")) { own_pty = 1; continue; }
        if (!v) usage();
        if (!strcmp(a, "--uart-fd")) uart_fd = atoi(v);
        else if (!strcmp(a, "--bridge-fd")) bridge_fd = atoi(v);
        else if (!strcmp(a, "--nvm")) nvm_path = v;
        else if (!strcmp(a, "--can")) can_node = atoi(v);
        else if (!strcmp(a, "--fw")) fw = v;
        else if (!strcmp(a, "--nvm-tear-after")) host.nvm.tear_after = atol(v);
        else usage();
        i++;
    }
    if (bridge_fd < 0 || !nvm_path || (uart_fd < 0) == !own_pty || can_node < 0 || can_node > 127) usage();
    if (own_pty && (uart_fd = open_own_pty()) < 0) { perror("fwboard: pty"); return 1; }
    if (host_nvm_open(&host.nvm, nvm_path) != 0) { perror("fwboard: nvm"); return 1; }
    make_raw(uart_fd);
    fcntl(uart_fd, F_SETFL, fcntl(uart_fd, F_GETFL) | O_NONBLOCK);
    host.link.fd = uart_fd;

    sigset_t block, unblocked;
    sigemptyset(&block);
    sigaddset(&block, SIGTERM);
    sigaddset(&block, SIGINT);
    sigprocmask(SIG_BLOCK, &block, &unblocked);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_term;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    fw_hal_t hal = { &host, NULL, NULL, host_nvm_read, host_nvm_write };
    if (can_node) hal.can_send = host_can_send; else hal.uart_write = host_uart_write;
    fw_linebuf_t bridge_lines;
    memset(&bridge_lines, 0, sizeof bridge_lines);
    int booted = 0;
    uint8_t buf[4096];

    while (!stop_requested) {
        if (host.link.hup && now_s() - hup_since > 0.2) host.link.hup = 0;   /* retry a hung-up station link */
        struct pollfd p[2];
        int np = 0, ui = -1;
        p[np++] = (struct pollfd){ bridge_fd, POLLIN, 0 };
        if (booted && !host.link.hup) {
            ui = np;
            p[np++] = (struct pollfd){ uart_fd, (short)(POLLIN | (host_link_pending(&host.link) ? POLLOUT : 0)), 0 };
        }
        struct timespec ts = { 0, 200000000 }, *tmo = host.link.hup ? &ts : NULL;
        int r = ppoll(p, (nfds_t)np, tmo, &unblocked);
        if (r < 0) { if (errno == EINTR) continue; perror("fwboard: poll"); break; }
        if (r == 0) continue;
        if (ui >= 0 && p[ui].revents) {
            if (p[ui].revents & POLLOUT) host_link_flush(&host.link);
            if (p[ui].revents & (POLLIN | POLLHUP | POLLERR)) {
                ssize_t n = read(uart_fd, buf, sizeof buf);
                if (n > 0) {
                    if (can_node) host_slcan_rx(&host.link, &board, buf, (uint32_t)n);
                    else fw_uart_rx(&board, buf, (uint32_t)n);
                } else if (n == 0 || (errno != EAGAIN && errno != EINTR)) {
                    host.link.hup = 1;   /* no station on the pty right now */
                    hup_since = now_s();
                }
            }
        }
        if (p[0].revents) {
            ssize_t n = read(bridge_fd, buf, sizeof buf);
            if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) break;   /* simulator gone */
            for (ssize_t i = 0; i < n; i++) {
                const uint8_t *line;
                uint32_t len;
                if (fw_linebuf_push(&bridge_lines, buf[i], &line, &len) != 1) continue;
                fw_identity_t id;
                fw_raw_sample_t s;
                int kind = fw_bridge_line(line, len, &id, &s);
                if (kind == FW_BRIDGE_IDENTITY && !booted) {
                    if (fw) { strncpy(id.fw, fw, FW_FW_MAX); id.fw[FW_FW_MAX] = 0; }
                    fw_board_init(&board, &hal, &id, (uint8_t)can_node);
                    booted = 1;
                    uint8_t ready[16];
                    write_all(bridge_fd, ready, fw_bridge_ready(ready, sizeof ready));
                } else if (kind == FW_BRIDGE_SAMPLE && booted) {
                    fw_sample(&board, &s);
                }
            }
        }
    }
    host_link_flush(&host.link);
    return 0;
}
