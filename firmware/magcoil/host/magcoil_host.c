/*
 * magcoil_host — the coil board's firmware (magcoil.c) on a POSIX host, behind a pseudo-terminal.
 *
 * The simulated hardware of the tests and of the lab server's simulated world: the same magcoil_step()
 * as on the board, fed from a pty (the "serial port"), with the outputs read over a control channel.
 *
 *   magcoil_host [--clock monotonic|external]
 *
 * stdout, first line:   {"pty": "/dev/pts/N"}          (open that path as the board's serial port)
 * stdin, control lines (one JSON object per line answered on stdout):
 *   t <microseconds>    external clock only: set the board's clock (never backwards), run the
 *                       deadline check, answer with the outputs
 *   q                   answer with the outputs: {"t_us", "dc_A", "ac_A", "freq_Hz", "tripped", "armed",
 *                       "seq", "deadline_us", "output_writes", "counters": {...}}
 * EOF on stdin ends the program (exit 0).
 *
 * --clock external: the board's clock moves only with "t" (deterministic tests). Before any control
 * command is answered, every byte readable on the pty is processed at the current clock.
 * --clock monotonic: CLOCK_MONOTONIC microseconds since start; the deadline is checked every 1 ms.
 *
 * Ratings, the maximum and default deadline are compile-time options (-DMAGCOIL_..., magcoil.h),
 * as on the board.
 */
#define _XOPEN_SOURCE 600

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "../magcoil.h"

static magcoil_t board;
static unsigned long long output_writes;
static int external_clock = 1;
static unsigned long long clock_us;      /* the board's time (external) or since start (monotonic) */
static struct timespec t_start;

void magcoil_output(const magcoil_outputs_t *o, void *ctx)
{
    (void)o;
    (void)ctx;
    output_writes++;
}

static unsigned long long now_us(void)
{
    struct timespec t;
    if (external_clock) {
        return clock_us;
    }
    clock_gettime(CLOCK_MONOTONIC, &t);
    clock_us = (unsigned long long)((long long)(t.tv_sec - t_start.tv_sec) * 1000000LL
                                    + (long long)((t.tv_nsec - t_start.tv_nsec) / 1000L));
    return clock_us;
}

/* The board's uint32 clock: the host's microseconds modulo 2^32 (wraps like micros()). */
static uint32_t board_clock(void) { return (uint32_t)(now_us() & 0xFFFFFFFFull); }

/* Replies go to the pty like bytes to a UART: never blocking; what the peer does not read is lost. */
static void send_all(int fd, const uint8_t *p, size_t n)
{
    while (n > 0) {
        ssize_t w = write(fd, p, n);
        if (w < 0) {
            if (errno == EINTR) {
                continue;
            }
            return;
        }
        p += w;
        n -= (size_t)w;
    }
}

static void step(int master, const uint8_t *rx, size_t n)
{
    uint8_t tx[16 * MAGCOIL_MAX_REPLY];
    size_t m = magcoil_step(&board, board_clock(), rx, n, tx, sizeof tx);
    if (m > 0) {
        send_all(master, tx, m);
    }
}

/* Process every byte readable on the pty master now (non-blocking). */
static void drain_pty(int master)
{
    uint8_t buf[256];
    for (;;) {
        ssize_t r = read(master, buf, sizeof buf);
        if (r > 0) {
            step(master, buf, (size_t)r);
            continue;
        }
        if (r < 0 && errno == EINTR) {
            continue;
        }
        return; /* EAGAIN: empty; EIO: no peer */
    }
}

static void print_amps(const char *key, const int32_t *ua)
{
    unsigned k;
    printf("\"%s\":[", key);
    for (k = 0; k < MAGCOIL_NCH; k++) {
        long long v = ua[k];
        unsigned long long m = (unsigned long long)(v < 0 ? -v : v);
        printf("%s%s%llu.%06llu", k ? "," : "", v < 0 ? "-" : "", m / 1000000ull, m % 1000000ull);
    }
    printf("]");
}

static void print_outputs(void)
{
    const magcoil_counters_t *c = &board.cnt;
    printf("{\"t_us\":%llu,", clock_us);
    print_amps("dc_A", board.out.dc_ua);
    printf(",");
    print_amps("ac_A", board.out.ac_ua);
    printf(",\"freq_Hz\":%lu.%03lu,\"tripped\":%s,\"armed\":%s,\"seq\":%u,\"deadline_us\":%lu,"
           "\"output_writes\":%llu,",
           (unsigned long)(board.out.freq_mhz / 1000u), (unsigned long)(board.out.freq_mhz % 1000u),
           board.tripped ? "true" : "false", board.armed ? "true" : "false", (unsigned)board.last_seq,
           (unsigned long)board.deadline_us, output_writes);
    printf("\"counters\":{\"frames_ok\":%lu,\"crc_errors\":%lu,\"malformed\":%lu,\"rejected\":%lu,"
           "\"deadline_trips\":%lu,\"tx_dropped\":%lu}}\n",
           (unsigned long)c->frames_ok, (unsigned long)c->crc_errors, (unsigned long)c->malformed,
           (unsigned long)c->rejected, (unsigned long)c->deadline_trips, (unsigned long)c->tx_dropped);
    fflush(stdout);
}

static void error_line(const char *msg)
{
    printf("{\"error\":\"%s\"}\n", msg);
    fflush(stdout);
}

static void control(int master, char *line)
{
    drain_pty(master); /* every byte the peer wrote before this command is processed at the old clock */
    if (line[0] == 'q' && (line[1] == '\0' || line[1] == ' ')) {
        now_us();
        step(master, NULL, 0);
        print_outputs();
    } else if (line[0] == 't' && line[1] == ' ') {
        char *end;
        unsigned long long t;
        if (!external_clock) {
            error_line("t needs --clock external");
            return;
        }
        errno = 0;
        t = strtoull(line + 2, &end, 10);
        if (errno != 0 || end == line + 2 || *end != '\0') {
            error_line("t needs an integer number of microseconds");
            return;
        }
        if (t < clock_us) {
            error_line("the clock must not go backwards");
            return;
        }
        clock_us = t;
        step(master, NULL, 0);
        print_outputs();
    } else {
        error_line("unknown command (t <us> | q)");
    }
}

/* Open a pty pair; the slave is set raw and kept open here, so the master never sees a hang-up when the
 * peer closes and reopens the port. */
static int open_pty(int *slave_out)
{
    int master = posix_openpt(O_RDWR | O_NOCTTY);
    const char *name;
    int slave;
    struct termios tio;
    if (master < 0 || grantpt(master) != 0 || unlockpt(master) != 0 || (name = ptsname(master)) == NULL) {
        perror("magcoil_host: posix_openpt");
        exit(1);
    }
    slave = open(name, O_RDWR | O_NOCTTY);
    if (slave < 0 || tcgetattr(slave, &tio) != 0) {
        perror("magcoil_host: open pty slave");
        exit(1);
    }
    tio.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF);
    tio.c_oflag &= ~(tcflag_t)OPOST;
    tio.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    tio.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
    tio.c_cflag |= (tcflag_t)CS8;
    tio.c_cc[VMIN] = 1;
    tio.c_cc[VTIME] = 0;
    if (tcsetattr(slave, TCSANOW, &tio) != 0 || tcsetattr(master, TCSANOW, &tio) != 0) {
        perror("magcoil_host: raw mode");
        exit(1);
    }
    if (fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK) != 0) {
        perror("magcoil_host: O_NONBLOCK");
        exit(1);
    }
    printf("{\"pty\": \"%s\"}\n", name);
    fflush(stdout);
    *slave_out = slave;
    return master;
}

int main(int argc, char **argv)
{
    int i, master, slave;
    char line[256];
    size_t line_len = 0;
    int line_overflow = 0;
    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--clock") == 0 && i + 1 < argc) {
            i++;
            if (strcmp(argv[i], "external") == 0) {
                external_clock = 1;
            } else if (strcmp(argv[i], "monotonic") == 0) {
                external_clock = 0;
            } else {
                fprintf(stderr, "magcoil_host: --clock external|monotonic\n");
                return 2;
            }
        } else {
            fprintf(stderr, "usage: magcoil_host [--clock external|monotonic]\n");
            return 2;
        }
    }
    clock_gettime(CLOCK_MONOTONIC, &t_start);
    magcoil_init(&board, NULL);
    master = open_pty(&slave);
    for (;;) {
        struct pollfd pfd[2];
        pfd[0].fd = master;
        pfd[0].events = POLLIN;
        pfd[1].fd = STDIN_FILENO;
        pfd[1].events = POLLIN;
        if (poll(pfd, 2, external_clock ? -1 : 1) < 0 && errno != EINTR) {
            perror("magcoil_host: poll");
            return 1;
        }
        if (pfd[0].revents & POLLIN) {
            drain_pty(master);
        }
        if (!external_clock) {
            step(master, NULL, 0); /* the deadline runs on the clock, not on traffic */
        }
        if (pfd[1].revents & (POLLIN | POLLHUP | POLLERR)) {
            char buf[256];
            ssize_t r = read(STDIN_FILENO, buf, sizeof buf);
            ssize_t j;
            if (r == 0 || (r < 0 && errno != EINTR && errno != EAGAIN)) {
                break; /* EOF: the controlling process is gone */
            }
            for (j = 0; j < r; j++) {
                if (buf[j] == '\n') {
                    line[line_len] = '\0';
                    if (line_overflow) {
                        error_line("line too long");
                    } else if (line_len > 0) {
                        control(master, line);
                    }
                    line_len = 0;
                    line_overflow = 0;
                } else if (buf[j] != '\r') {
                    if (line_len + 1 < sizeof line) {
                        line[line_len++] = buf[j];
                    } else {
                        line_overflow = 1;
                    }
                }
            }
        }
    }
    close(slave);
    close(master);
    return 0;
}
