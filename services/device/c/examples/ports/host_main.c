/* The POSIX port of the example devices (thermostat, robot): the transport around the sans-IO core.
 *
 *   DEVICE --tcp HOST:PORT       serve one TCP connection at a time (port 0: a free one); each new
 *                                connection is a new session and gets the greeting first
 *   DEVICE --pty                 make a pseudo-terminal and serve its master end; prints the path
 *                                of the end to give the gateway (serial:///dev/pts/N)
 *   DEVICE --serial PATH         serve a serial port (raw, 115200 baud)
 *   DEVICE --connect HOST:PORT
 *                                dial a gateway's line listener and greet (the device registers
 *                                itself there); when the connection ends, or the gateway stays
 *                                silent past the keep-alive, dial the next gateway it named in its
 *                                greeting (alternates=HOST:PORT,...), in turn (docs/line-protocol.md
 *                                §4.5, §9)
 *   --period MS                  the device's timer (example_tick; default 500)
 *   --keepalive MS               with --connect: PING a gateway silent this long (default 2000)
 *   --keepalive-timeout MS       ... and leave it when nothing comes back within this (default 3000)
 *
 * It prints "listening on HOST:PORT", "serial port PATH" or "connecting to HOST:PORT" once ready. SIGUSR1 resets the device
 * as a reset button would (every value to its default, the greeting again on the same line);
 * SIGTERM and SIGINT end it.
 */
#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "example.h"

static volatile sig_atomic_t reset_requested, stop_requested;
static int line_fd = -1; /* where lines go: the connection, the pty master or the serial port */
static char pending_out[1024];
static size_t pending_length;

static void on_signal(int sig) {
    if (sig == SIGUSR1) reset_requested = 1;
    else stop_requested = 1;
}

static void flush_out(void) {
    size_t done = 0;
    while (line_fd >= 0 && done < pending_length) {
        ssize_t n = write(line_fd, pending_out + done, pending_length - done);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) break; /* the peer is gone: the read side notices and ends the session */
        done += (size_t)n;
    }
    pending_length = 0;
}

/* The core's byte sink: collect a line, write it whole at its LF. */
static void put_byte(void *context, uint8_t byte) {
    (void)context;
    pending_out[pending_length++] = (char)byte;
    if (byte == '\n' || pending_length == sizeof pending_out) flush_out();
}

static long long now_ms(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

static int make_raw(int fd) {
    struct termios tio;
    if (tcgetattr(fd, &tio) != 0) return -1;
    cfmakeraw(&tio);
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    return tcsetattr(fd, TCSANOW, &tio);
}

static int open_tcp(const char *address) {
    char host[64];
    const char *colon = strrchr(address, ':');
    if (!colon || (size_t)(colon - address) >= sizeof host) return -1;
    memcpy(host, address, (size_t)(colon - address));
    host[colon - address] = 0;
    struct sockaddr_in sa;
    memset(&sa, 0, sizeof sa);
    sa.sin_family = AF_INET;
    sa.sin_port = htons((uint16_t)atoi(colon + 1));
    if (inet_pton(AF_INET, host, &sa.sin_addr) != 1) return -1;
    int fd = socket(AF_INET, SOCK_STREAM, 0), one = 1;
    if (fd < 0) return -1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    socklen_t len = sizeof sa;
    if (bind(fd, (struct sockaddr *)&sa, sizeof sa) != 0 || listen(fd, 1) != 0 ||
        getsockname(fd, (struct sockaddr *)&sa, &len) != 0) {
        close(fd);
        return -1;
    }
    printf("listening on %s:%u\n", host, ntohs(sa.sin_port));
    return fd;
}

/* ---- dialling a gateway, and the next one when it is gone or frozen ----------------------------- */

#define MAX_GATEWAYS 16
static char gateways[MAX_GATEWAYS][64]; /* [0] what the device was started with (kept last in turn) */
static int gateway_count = 1, next_gateway;
static char first_line[512]; /* the gateway's greeting, read for its alternates= */
static size_t first_length;
static int first_done;

static int dial(const char *address) {
    char host[64];
    const char *colon = strrchr(address, ':');
    if (!colon || (size_t)(colon - address) >= sizeof host) return -1;
    memcpy(host, address, (size_t)(colon - address));
    host[colon - address] = 0;
    struct sockaddr_in sa;
    memset(&sa, 0, sizeof sa);
    sa.sin_family = AF_INET;
    sa.sin_port = htons((uint16_t)atoi(colon + 1));
    if (inet_pton(AF_INET, host, &sa.sin_addr) != 1) return -1;
    int fd = socket(AF_INET, SOCK_STREAM, 0);
    if (fd < 0) return -1;
    if (connect(fd, (struct sockaddr *)&sa, sizeof sa) != 0) {
        close(fd);
        return -1;
    }
    return fd;
}

/* The gateway's greeting names the others: the turn is now this gateway, its alternates, then the
 * address given at the start; the next to dial is the first alternate. */
static void take_alternates(const char *current) {
    const char *field = strstr(first_line, " alternates=");
    if (strncmp(first_line, "HELLO ", 6) != 0 || !field) return;
    char list[MAX_GATEWAYS][64];
    int count = 0;
    snprintf(list[count++], sizeof list[0], "%s", current);
    for (const char *p = field + 12; *p && *p != ' ' && *p != '\r' && *p != '\n' && count < MAX_GATEWAYS - 1;) {
        size_t n = strcspn(p, ", \r\n");
        if (n > 0 && n < sizeof list[0]) {
            memcpy(list[count], p, n);
            list[count][n] = 0;
            if (strcmp(list[count], current) != 0) count++;
        }
        p += n;
        if (*p == ',') p++;
    }
    int given_listed = 0;
    for (int i = 0; i < count; i++) given_listed |= strcmp(list[i], gateways[0]) == 0;
    if (!given_listed) snprintf(list[count++], sizeof list[0], "%s", gateways[0]);
    /* gateways[0] stays the address given; the turn is kept from [1] on */
    for (int i = 0; i < count && i + 1 < MAX_GATEWAYS; i++) memcpy(gateways[i + 1], list[i], sizeof list[0]);
    gateway_count = count + 1;
    next_gateway = count > 1 ? 2 : 1;
}

static void heard_first_line(const uint8_t *bytes, size_t n, const char *current) {
    for (size_t i = 0; i < n && !first_done; i++) {
        if (bytes[i] == '\n' || first_length == sizeof first_line - 1) {
            first_line[first_length] = 0;
            first_done = 1;
            take_alternates(current);
        } else {
            first_line[first_length++] = (char)bytes[i];
        }
    }
}

static const char *program = "device"; /* argv[0], for messages */

static int usage(void) {
    fprintf(stderr, "usage: %s (--tcp HOST:PORT | --pty | --serial PATH | --connect HOST:PORT) "
                    "[--period MS] [--keepalive MS] [--keepalive-timeout MS]\n", program);
    return 2;
}

int main(int argc, char **argv) {
    program = argv[0];
    const char *tcp = 0, *serial = 0, *connect_to = 0;
    int pty = 0;
    long period = 500, keepalive = 2000, keepalive_timeout = 3000;
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--tcp") == 0 && i + 1 < argc) tcp = argv[++i];
        else if (strcmp(argv[i], "--serial") == 0 && i + 1 < argc) serial = argv[++i];
        else if (strcmp(argv[i], "--connect") == 0 && i + 1 < argc) connect_to = argv[++i];
        else if (strcmp(argv[i], "--pty") == 0) pty = 1;
        else if (strcmp(argv[i], "--period") == 0 && i + 1 < argc) period = atol(argv[++i]);
        else if (strcmp(argv[i], "--keepalive") == 0 && i + 1 < argc) keepalive = atol(argv[++i]);
        else if (strcmp(argv[i], "--keepalive-timeout") == 0 && i + 1 < argc) keepalive_timeout = atol(argv[++i]);
        else return usage();
    }
    if ((tcp != 0) + (serial != 0) + pty + (connect_to != 0) != 1 || period < 1 || keepalive < 0 ||
        keepalive_timeout < 1)
        return usage();
    if (connect_to && strlen(connect_to) >= sizeof gateways[0]) return usage();
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGUSR1, &sa, 0);
    sigaction(SIGTERM, &sa, 0);
    sigaction(SIGINT, &sa, 0);
    signal(SIGPIPE, SIG_IGN);

    static ps_device dev;
    int server = -1, keep_slave = -1;
    if (tcp) {
        server = open_tcp(tcp);
        if (server < 0) {
            fprintf(stderr, "%s: cannot listen on %s: %s\n", program, tcp, strerror(errno));
            return 1;
        }
    } else if (pty) {
        line_fd = posix_openpt(O_RDWR | O_NOCTTY);
        if (line_fd < 0 || grantpt(line_fd) != 0 || unlockpt(line_fd) != 0) return perror("pty"), 1;
        const char *path = ptsname(line_fd);
        /* Keep the other end open: while nobody has it open, reading the master fails with EIO. */
        keep_slave = open(path, O_RDWR | O_NOCTTY);
        if (keep_slave < 0 || make_raw(keep_slave) != 0) return perror(path), 1;
        printf("serial port %s\n", path);
    } else if (connect_to) {
        snprintf(gateways[0], sizeof gateways[0], "%s", connect_to);
        printf("connecting to %s\n", connect_to);
    } else {
        line_fd = open(serial, O_RDWR | O_NOCTTY);
        if (line_fd < 0 || make_raw(line_fd) != 0) return perror(serial), 1;
        printf("serial port %s\n", serial);
    }
    fflush(stdout);
    example_start(&dev, put_byte, 0); /* on TCP nobody hears this one: each connection gets its own */

    long long next_tick = now_ms() + period;
    /* Dialling: when to dial next, the pause before a new round, what was last heard, the PING. */
    long long dial_at = 0, heard_at = 0, pinged_at = 0, pause = 200, connected_at = 0;
    int dialled_in_round = 0;
    char current[64] = "";
    while (!stop_requested) {
        if (reset_requested) {
            reset_requested = 0;
            example_start(&dev, put_byte, 0);
        }
        if (connect_to && line_fd < 0 && now_ms() >= dial_at) {
            if (next_gateway >= gateway_count || next_gateway == 0) next_gateway = gateway_count > 1 ? 1 : 0;
            snprintf(current, sizeof current, "%s", gateways[next_gateway++]);
            line_fd = dial(current);
            if (++dialled_in_round >= gateway_count) { /* every address tried: pause, doubling */
                dialled_in_round = 0;
                dial_at = now_ms() + pause;
                pause = pause * 2 > 10000 ? 10000 : pause * 2;
            }
            if (line_fd >= 0) {
                fprintf(stderr, "%s: connected to %s\n", program, current);
                first_length = 0, first_done = 0, heard_at = connected_at = now_ms(), pinged_at = 0;
                ps_begin(&dev, dev.config); /* the greeting registers the device there */
            }
        }
        struct pollfd pfd = {line_fd >= 0 ? line_fd : server, POLLIN, 0};
        long long wait = next_tick - now_ms();
        if (connect_to && line_fd < 0 && dial_at - now_ms() < wait) wait = dial_at - now_ms();
        if (connect_to && line_fd >= 0 && keepalive > 0) {
            long long due = pinged_at ? pinged_at + keepalive_timeout : heard_at + keepalive;
            if (due - now_ms() < wait) wait = due - now_ms();
        }
        int ready = poll(&pfd, pfd.fd >= 0 ? 1 : 0, wait < 0 ? 0 : (int)wait);
        if (ready < 0 && errno != EINTR) return perror("poll"), 1;
        if (ready > 0 && line_fd < 0) {
            line_fd = accept(server, 0, 0);
            if (line_fd >= 0) ps_begin(&dev, dev.config); /* a new session: greeting first */
        } else if (ready > 0) {
            uint8_t bytes[512];
            ssize_t n = read(line_fd, bytes, sizeof bytes);
            if (n > 0) {
                if (connect_to) {
                    heard_at = now_ms(), pinged_at = 0;
                    if (!first_done) heard_first_line(bytes, (size_t)n, current);
                }
                ps_feed(&dev, bytes, (size_t)n);
            } else if (n == 0 || errno != EINTR) {
                if (server < 0 && !connect_to) return n == 0 ? 0 : (perror("read"), 1);
                close(line_fd); /* the connection ended: wait for the next, or dial the next gateway */
                line_fd = -1;
                if (connect_to) {
                    fprintf(stderr, "%s: the connection to %s ended\n", program, current);
                    if (now_ms() - connected_at > 10000) dialled_in_round = 0, dial_at = 0, pause = 200;
                }
            }
        }
        if (connect_to && line_fd >= 0 && keepalive > 0) {
            long long now = now_ms();
            if (pinged_at && now - pinged_at >= keepalive_timeout) {
                /* A frozen gateway keeps the connection open but answers nothing: leave it (§9). */
                fprintf(stderr, "%s: %s did not answer a keep-alive PING; dialling the next\n", program,
                        current);
                close(line_fd);
                line_fd = -1;
                dialled_in_round = 0; /* it was up: the next gateway at once */
                dial_at = 0, pause = 200;
            } else if (!pinged_at && now - heard_at >= keepalive && pending_length == 0) {
                static const char ping[] = "PING keepalive\n";
                for (size_t i = 0; i < sizeof ping - 1; i++) put_byte(0, (uint8_t)ping[i]);
                pinged_at = now;
            }
        }
        if (now_ms() >= next_tick) {
            next_tick += period;
            example_tick(&dev);
        }
        ps_poll(&dev);
    }
    if (keep_slave >= 0) close(keep_slave);
    return 0;
}
