/* host_main.c: build/host/fwboard, the board firmware as a Linux process (one per board).
 *
 *   fwboard (--uart-fd N | --uart-pty) --bridge-fd N --nvm PATH [--can NODE] [--fw VERSION]
 *           [--nvm-tear-after BYTES] [--boot-cause WORD --boots N [--fault-pc HEX] [--resume S,HZ]]
 *
 * The station link is fd N (e.g. the master of a pty the parent made) or a pty made here (its
 * slave path printed as `PTY <path>` on stdout). Serial boards speak design 3.1 on it; with --can
 * it carries CAN frames as slcan lines `t<id><dlc><data>\r` both ways. The sensor bridge (fd N)
 * brings the identity strap and the samples (core/fw_bridge.h). poll() only, no busy loop; exits
 * on EOF of the bridge or SIGTERM.
 *
 * Recovery (issue 42), the host's stand-ins for the board's reset machinery:
 *   fault      `$X,hardfault` executes a trap instruction (SIGILL); its handler re-executes the
 *              process (execv of /proc/self/exe, every fd kept) with --boot-cause fault --boots N+1
 *              --fault-pc <the trapping address, low 32 bits> --resume <streaming>,<odr_hz>
 *   watchdog   a one-shot ITIMER_REAL of WDT_MS, re-armed whenever the loop made progress
 *              (streaming: samples taken or the liveness check ran; idle: the loop ran, poll()
 *              never sleeps longer than 250 ms); `$X,hang` stops the loop, SIGALRM re-executes
 *              with --boot-cause watchdog
 *   start      a first start reports reset=power, boots=1; a re-executed one sends `$BOOT*HH` on
 *              the bridge (the simulator answers with its `$B` strap) and, once booted, resumes
 *              streaming at the ODR it had. (A first start sends no `$BOOT`: its parent is already
 *              sending the strap.)
 *   liveness   while streaming, no sample within max(3 output periods, 250 ms) of CLOCK_MONOTONIC
 *              (poll()'s timeout is the tick) -> `$INIT*HH` on the bridge, fw_board_sensor_reinit.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <errno.h>
#include <fcntl.h>
#include <sys/time.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>
#include "fw_bridge.h"
#include "fw_health.h"
#include "host.h"

#define WDT_MS 1000
#define TICK_STREAM_MS 20
#define TICK_IDLE_MS 250
#define SILENCE_MIN_US 250000u   /* the bridge delivers samples in bursts (the simulator's ticks) */
#define MAX_ARGS 40

static volatile sig_atomic_t stop_requested;
static double hup_since;

/* ---- re-execution (the host's reset): argv prepared at start, numbers filled in by the handler ---- */
static char *reexec_argv[MAX_ARGS + 12];
static int reexec_argc;
static char reexec_boots[16], reexec_pc[16], reexec_resume[32];
static uint32_t cur_boots = 1;

static double now_s(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}
static void on_term(int sig) { (void)sig; stop_requested = 1; }

static fw_board_t board;
static host_ctx_t host;
static int booted;

/* async-signal-safe number formatting (no snprintf in a signal handler) */
static void fmt_dec(char *out, uint32_t v)
{
    char tmp[12];
    int n = 0, i = 0;
    do { tmp[n++] = (char)('0' + v % 10u); v /= 10u; } while (v && n < 11);
    while (n) out[i++] = tmp[--n];
    out[i] = 0;
}

static void fmt_hex8(char *out, uint32_t v)
{
    static const char HEX[] = "0123456789ABCDEF";
    for (int i = 0; i < 8; i++) out[i] = HEX[(v >> (28 - 4 * i)) & 15u];
    out[8] = 0;
}

/* The resume state: streaming flag and ODR in mHz ("1,33333" = streaming at 33.333 Hz). */
static void fmt_resume(char *out)
{
    out[0] = booted && board.streaming ? '1' : '0';
    out[1] = ',';
    fmt_dec(out + 2, booted ? (uint32_t)(board.odr_hz * 1000.0f + 0.5f) : 0u);
}

/* The board "resets": exec ourselves again with why. Only async-signal-safe calls. */
static void reexec(const char *cause, uint32_t fault_pc)
{
    int k = reexec_argc;
    fmt_dec(reexec_boots, cur_boots + 1u);
    fmt_hex8(reexec_pc, fault_pc);
    fmt_resume(reexec_resume);
    reexec_argv[k++] = (char *)"--boot-cause";
    reexec_argv[k++] = (char *)cause;
    reexec_argv[k++] = (char *)"--boots";
    reexec_argv[k++] = reexec_boots;
    reexec_argv[k++] = (char *)"--fault-pc";
    reexec_argv[k++] = reexec_pc;
    reexec_argv[k++] = (char *)"--resume";
    reexec_argv[k++] = reexec_resume;
    reexec_argv[k] = NULL;
    execv("/proc/self/exe", reexec_argv);
    _exit(70);   /* exec failed: the board is dead */
}

static void on_fault(int sig, siginfo_t *si, void *uc)
{
    (void)sig; (void)uc;
    reexec("fault", (uint32_t)(uintptr_t)si->si_addr);
}

static void on_watchdog(int sig) { (void)sig; reexec("watchdog", 0u); }

static void wdt_feed(void)
{
    struct itimerval it;
    memset(&it, 0, sizeof it);
    it.it_value.tv_sec = WDT_MS / 1000;
    it.it_value.tv_usec = (WDT_MS % 1000) * 1000;
    setitimer(ITIMER_REAL, &it, NULL);
}

static uint32_t now_us32(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint32_t)((uint64_t)t.tv_sec * 1000000u + (uint64_t)t.tv_nsec / 1000u);
}

__attribute__((noinline)) static void inject_hardfault(void) { __builtin_trap(); }
__attribute__((noinline)) static void inject_hang(void) { for (;;) pause(); }

static uint8_t cause_of(const char *w)
{
    for (uint8_t c = 0; c <= FW_RESET_SOFTWARE; c++) if (!strcmp(fw_reset_word(c), w)) return c;
    return FW_RESET_UNKNOWN;
}

static void usage(void)
{
    fprintf(stderr, "usage: fwboard (--uart-fd N | --uart-pty) --bridge-fd N --nvm PATH [--can NODE] "
                    "[--fw VERSION] [--nvm-tear-after BYTES] [--boot-cause WORD --boots N [--fault-pc HEX] "
                    "[--resume S,MHZ]]\n");
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

/* Streaming again at the ODR it had before the re-execution (the core's public fields, as
 * fw_set_decimation sets them: there is no core call for a resume). */
static void resume(uint32_t odr_mhz)
{
    float odr = (float)odr_mhz / 1000.0f;
    if (odr > 0.0f && odr < board.id.odr_hz) {
        uint32_t decim = (uint32_t)(board.id.odr_hz / odr + 0.5f);
        if (decim > 1u) {
            board.decim = decim;
            board.phase = 0;
            board.odr_hz = board.id.odr_hz / (float)decim;
        }
    }
    board.streaming = 1;
}

int main(int argc, char **argv)
{
    int uart_fd = -1, bridge_fd = -1, own_pty = 0, can_node = 0, reexeced = 0, resume_streaming = 0;
    uint32_t resume_mhz = 0;
    const char *nvm_path = NULL, *fw = NULL;
    fw_boot_info_t boot = { FW_RESET_POWER, 1u, 0u, 0u };
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
        else if (!strcmp(a, "--boot-cause")) { boot.cause = cause_of(v); reexeced = 1; }
        else if (!strcmp(a, "--boots")) boot.boots = (uint32_t)strtoul(v, NULL, 10);
        else if (!strcmp(a, "--fault-pc")) boot.fault_pc = (uint32_t)strtoul(v, NULL, 16);
        else if (!strcmp(a, "--resume")) {
            char *end;
            resume_streaming = (int)strtol(v, &end, 10);
            resume_mhz = *end == ',' ? (uint32_t)strtoul(end + 1, NULL, 10) : 0u;
        }
        else usage();
        i++;
    }
    if (bridge_fd < 0 || !nvm_path || (uart_fd < 0) == !own_pty || can_node < 0 || can_node > 127) usage();
    if (boot.cause != FW_RESET_FAULT) boot.fault_pc = 0;
    cur_boots = boot.boots;
    if (own_pty && (uart_fd = open_own_pty()) < 0) { perror("fwboard: pty"); return 1; }

    /* the argv of a re-execution: ours without the boot arguments, our pty as --uart-fd */
    static char uart_fd_text[16];
    fmt_dec(uart_fd_text, (uint32_t)uart_fd);
    reexec_argv[reexec_argc++] = argv[0];
    for (int i = 1; i < argc && reexec_argc < MAX_ARGS; i++) {
        const char *a = argv[i];
        if (!strcmp(a, "--uart-pty")) { reexec_argv[reexec_argc++] = (char *)"--uart-fd"; reexec_argv[reexec_argc++] = uart_fd_text; continue; }
        if (!strcmp(a, "--boot-cause") || !strcmp(a, "--boots") || !strcmp(a, "--fault-pc") || !strcmp(a, "--resume")
            || !strcmp(a, "--nvm-tear-after")) { i++; continue; }
        reexec_argv[reexec_argc++] = argv[i];
        if (i + 1 < argc) reexec_argv[reexec_argc++] = argv[++i];
    }
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
    /* a re-executed process inherits the mask of the handler that exec'd it: unblock both */
    sigset_t resets;
    sigemptyset(&resets);
    sigaddset(&resets, SIGALRM);
    sigaddset(&resets, SIGILL);
    sigprocmask(SIG_UNBLOCK, &resets, NULL);
    struct sigaction fa;
    memset(&fa, 0, sizeof fa);
    fa.sa_sigaction = on_fault;
    fa.sa_flags = SA_SIGINFO;
    sigaction(SIGILL, &fa, NULL);
    struct sigaction wa;
    memset(&wa, 0, sizeof wa);
    wa.sa_handler = on_watchdog;
    sigaction(SIGALRM, &wa, NULL);
    wdt_feed();

    fw_hal_t hal = { &host, NULL, NULL, host_nvm_read, host_nvm_write };
    if (can_node) hal.can_send = host_can_send; else hal.uart_write = host_uart_write;
    fw_linebuf_t bridge_lines;
    memset(&bridge_lines, 0, sizeof bridge_lines);
    uint8_t buf[4096];
    fw_health_t health;
    fw_health_init(&health, 0u, SILENCE_MIN_US);
    uint32_t taken_since_feed = 0;
    if (reexeced) {
        uint8_t out[16];
        write_all(bridge_fd, out, fw_bridge_boot(out, sizeof out));
    }

    while (!stop_requested) {
        /* the last pass's bytes and samples are handled: finish a long reply (core/fw_board.h) before
         * poll() sleeps (the per-sample path formats it a few numbers at a time otherwise) */
        if (booted) fw_board_idle(&board);
        if (host.link.hup && now_s() - hup_since > 0.2) host.link.hup = 0;   /* retry a hung-up station link */
        /* liveness: while streaming, no sample within the deadline -> re-init the (bridge) sensor */
        int health_ran = 0;
        if (booted) {
            fw_health_verdict_t v = fw_health_poll(&health, now_us32(), fw_board_period_us(&board), fw_board_streaming(&board));
            if (v == FW_HEALTH_SUSPECT) {   /* no WHO_AM_I on the bridge: straight on to the re-init */
                fw_health_who_am_i(&health, 1);
                v = fw_health_poll(&health, now_us32(), fw_board_period_us(&board), 1);
            }
            if (v == FW_HEALTH_REINIT) {
                uint8_t out[16];
                uint32_t silent_ms = fw_health_silent_ms(&health, now_us32());
                write_all(bridge_fd, out, fw_bridge_init(out, sizeof out));
                fw_health_reinit_done(&health, now_us32());
                fw_board_sensor_reinit(&board, silent_ms);
            }
            health_ran = 1;
        }
        /* fed only for progress: idle, the loop ran; streaming, samples taken or the check ran */
        if (!booted || !fw_board_streaming(&board) || taken_since_feed > 0 || health_ran) {
            wdt_feed();
            taken_since_feed = 0;
        }
        struct pollfd p[2];
        int np = 0, ui = -1;
        p[np++] = (struct pollfd){ bridge_fd, POLLIN, 0 };
        if (booted && !host.link.hup) {
            ui = np;
            p[np++] = (struct pollfd){ uart_fd, (short)(POLLIN | (host_link_pending(&host.link) ? POLLOUT : 0)), 0 };
        }
        int tick_ms = booted && fw_board_streaming(&board) ? TICK_STREAM_MS : TICK_IDLE_MS;
        if (host.link.hup && tick_ms > 200) tick_ms = 200;
        struct timespec ts = { 0, (long)tick_ms * 1000000L };
        int r = ppoll(p, (nfds_t)np, &ts, &unblocked);
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
                fw_bridge_fault_t x;
                if (kind == FW_BRIDGE_IDENTITY) {
                    if (!booted) {
                        if (fw) { strncpy(id.fw, fw, FW_FW_MAX); id.fw[FW_FW_MAX] = 0; }
                        fw_board_init(&board, &hal, &id, (uint8_t)can_node);
                        fw_board_set_boot(&board, &boot);
                        booted = 1;
                        if (resume_streaming) resume(resume_mhz);
                    }
                    uint8_t ready[16];
                    write_all(bridge_fd, ready, fw_bridge_ready(ready, sizeof ready));
                } else if (kind == FW_BRIDGE_SAMPLE && booted) {
                    fw_sample(&board, &s);
                    fw_health_data_ready(&health, now_us32());
                    taken_since_feed++;
                } else if (kind == FW_BRIDGE_NONE && fw_bridge_fault(line, len, &x) == FW_BRIDGE_FAULT) {
                    if (x.kind == FW_FAULT_HARDFAULT) inject_hardfault();
                    else if (x.kind == FW_FAULT_HANG) inject_hang();
                    else if (x.kind == FW_FAULT_SELFCAL_SKEW && booted) fw_board_selfcal_skew(&board, x.value);
                }
            }
        }
    }
    host_link_flush(&host.link);
    return 0;
}
