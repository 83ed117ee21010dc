/* The example device on a POSIX host: the transport around the sans-IO core.
 *
 *   thermostat --tcp HOST:PORT   serve one TCP connection at a time (port 0: a free one); each new
 *                                connection is a new session and gets the greeting first
 *   thermostat --pty             make a pseudo-terminal and serve its master end; prints the path
 *                                of the end to give the gateway (serial:///dev/pts/N)
 *   thermostat --serial PATH     serve a serial port (raw, 115200 baud)
 *   --period MS                  the timer that changes temp (default 500)
 *
 * It prints "listening on HOST:PORT" or "serial port PATH" once ready. SIGUSR1 resets the device
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

#include "thermostat.h"

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

static int usage(void) {
    fprintf(stderr, "usage: thermostat (--tcp HOST:PORT | --pty | --serial PATH) [--period MS]\n");
    return 2;
}

int main(int argc, char **argv) {
    const char *tcp = 0, *serial = 0;
    int pty = 0;
    long period = 500;
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--tcp") == 0 && i + 1 < argc) tcp = argv[++i];
        else if (strcmp(argv[i], "--serial") == 0 && i + 1 < argc) serial = argv[++i];
        else if (strcmp(argv[i], "--pty") == 0) pty = 1;
        else if (strcmp(argv[i], "--period") == 0 && i + 1 < argc) period = atol(argv[++i]);
        else return usage();
    }
    if ((tcp != 0) + (serial != 0) + pty != 1 || period < 1) return usage();
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
            fprintf(stderr, "thermostat: cannot listen on %s: %s\n", tcp, strerror(errno));
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
    } else {
        line_fd = open(serial, O_RDWR | O_NOCTTY);
        if (line_fd < 0 || make_raw(line_fd) != 0) return perror(serial), 1;
        printf("serial port %s\n", serial);
    }
    fflush(stdout);
    thermostat_start(&dev, put_byte, 0); /* on TCP nobody hears this one: each connection gets its own */

    long long next_tick = now_ms() + period;
    while (!stop_requested) {
        if (reset_requested) {
            reset_requested = 0;
            thermostat_start(&dev, put_byte, 0);
        }
        struct pollfd pfd = {line_fd >= 0 ? line_fd : server, POLLIN, 0};
        long long wait = next_tick - now_ms();
        int ready = poll(&pfd, 1, wait < 0 ? 0 : (int)wait);
        if (ready < 0 && errno != EINTR) return perror("poll"), 1;
        if (ready > 0 && line_fd < 0) {
            line_fd = accept(server, 0, 0);
            if (line_fd >= 0) ps_begin(&dev, dev.config); /* a new session: greeting first */
        } else if (ready > 0) {
            uint8_t bytes[512];
            ssize_t n = read(line_fd, bytes, sizeof bytes);
            if (n > 0) {
                ps_feed(&dev, bytes, (size_t)n);
            } else if (n == 0 || errno != EINTR) {
                if (server < 0) return n == 0 ? 0 : (perror("read"), 1);
                close(line_fd); /* the connection ended: wait for the next */
                line_fd = -1;
            }
        }
        if (now_ms() >= next_tick) {
            next_tick += period;
            thermostat_tick(&dev);
        }
        ps_poll(&dev);
    }
    if (keep_slave >= 0) close(keep_slave);
    return 0;
}
