package main

import (
	"context"
	"errors"
	"fmt"
	"io"
	"net"
	"sync"
	"syscall"
	"time"
	"unsafe"
)

// The gateways write each event as it is ready, tens of microseconds apart. A reader that the
// kernel wakes for each of them pays a wakeup of the process (epoll, a read, two context switches)
// per event, which costs more than grpc-go's handling of the event; Go's network poller wakes the
// process for every arrival on a connection it watches, whether or not a goroutine waits for it.
// So the connections here are kept out of the poller: each is read with non-blocking reads on one
// tick shared by the process, and one wakeup takes in what arrived on all of them since the last.
// A read that fills the buffer is followed by another at once. What waits meanwhile sits in the
// kernel's socket buffer (a few KiB at the benchmark's rates; the flow-control windows are far
// larger), so the gateways neither wait nor see a slower reader: only what reading costs here
// changes, and a stream's events are counted at most one tick late, at the start as at the stop.

// pacer closes a channel every tick: every goroutine waiting on it wakes with the others.
type pacer struct {
	mu   sync.Mutex
	next chan struct{}
}

func newPacer(tick time.Duration) *pacer {
	p := &pacer{next: make(chan struct{})}
	go func() {
		for range time.NewTicker(tick).C {
			p.mu.Lock()
			close(p.next)
			p.next = make(chan struct{})
			p.mu.Unlock()
		}
	}()
	return p
}

// wait returns at the next tick.
func (p *pacer) wait() {
	p.mu.Lock()
	next := p.next
	p.mu.Unlock()
	<-next
}

// dial connects to address over TCP and hands the connection over to a pacedConn.
func (p *pacer) dial(ctx context.Context, address string) (net.Conn, error) {
	conn, err := (&net.Dialer{}).DialContext(ctx, "tcp", address)
	if err != nil {
		return nil, err
	}
	defer conn.Close() // the duplicate below carries the connection on
	tcp, ok := conn.(*net.TCPConn)
	if !ok {
		return nil, fmt.Errorf("dialling %s gave a %T, not a TCP connection", address, conn)
	}
	raw, err := tcp.SyscallConn()
	if err != nil {
		return nil, err
	}
	// A duplicate descriptor that the poller does not watch (closing the original takes the
	// connection out of it); it shares the original's non-blocking mode. (TCPConn.File would hand
	// the duplicate to the poller again.)
	fd, dupErr := -1, error(nil)
	if err := raw.Control(func(original uintptr) { fd, dupErr = syscall.Dup(int(original)) }); err != nil {
		return nil, err
	}
	if dupErr != nil {
		return nil, dupErr
	}
	return &pacedConn{fd: fd, pacer: p, local: tcp.LocalAddr(), remote: tcp.RemoteAddr()}, nil
}

// pacedConn is a TCP connection read on the pacer's tick with non-blocking system calls. grpc-go
// reads a connection from one goroutine, so full needs no lock; mu keeps Close from closing the
// descriptor (whose number the system may then give to another file) under a read or a write.
type pacedConn struct {
	fd            int
	pacer         *pacer
	local, remote net.Addr
	mu            sync.RWMutex
	closed        bool
	full          bool
}

// call runs one system call on the descriptor unless the connection is closed.
func (c *pacedConn) call(do func(fd int) (int, error)) (int, error) {
	c.mu.RLock()
	defer c.mu.RUnlock()
	if c.closed {
		return 0, net.ErrClosed
	}
	return do(c.fd)
}

// rawCall reads or writes b, which is not empty, without telling the scheduler: the call cannot
// block (the descriptor is non-blocking). A call the scheduler knows of gives the thread's processor
// to another thread when it has taken more than 20 µs, as calls often do on a busy machine, and that
// hand-off and the one back cost two context switches.
func rawCall(call uintptr, fd int, b []byte) (int, error) {
	n, _, errno := syscall.RawSyscall(call, uintptr(fd), uintptr(unsafe.Pointer(&b[0])), uintptr(len(b)))
	if errno != 0 {
		return 0, errno
	}
	return int(n), nil
}

func (c *pacedConn) Read(b []byte) (int, error) {
	for {
		if !c.full {
			c.pacer.wait()
		}
		n, err := c.call(func(fd int) (int, error) { return rawCall(syscall.SYS_READ, fd, b) })
		switch {
		case errors.Is(err, syscall.EAGAIN):
			c.full = false
		case errors.Is(err, syscall.EINTR):
		case err != nil:
			return 0, err
		case n == 0:
			return 0, io.EOF
		default:
			c.full = n == len(b)
			return n, nil
		}
	}
}

func (c *pacedConn) Write(b []byte) (int, error) {
	written := 0
	for written < len(b) {
		n, err := c.call(func(fd int) (int, error) { return rawCall(syscall.SYS_WRITE, fd, b[written:]) })
		switch {
		case errors.Is(err, syscall.EAGAIN):
			c.pacer.wait() // the socket's send buffer is full: it drains meanwhile
		case errors.Is(err, syscall.EINTR):
		case err != nil:
			return written, err
		default:
			written += n
		}
	}
	return written, nil
}

func (c *pacedConn) Close() error {
	c.mu.Lock()
	defer c.mu.Unlock()
	if c.closed {
		return nil
	}
	c.closed = true
	return syscall.Close(c.fd)
}

func (c *pacedConn) LocalAddr() net.Addr  { return c.local }
func (c *pacedConn) RemoteAddr() net.Addr { return c.remote }

// Deadlines are not kept: grpc-go's client only clears one, and every wait here ends at a tick.
func (c *pacedConn) SetDeadline(time.Time) error      { return nil }
func (c *pacedConn) SetReadDeadline(time.Time) error  { return nil }
func (c *pacedConn) SetWriteDeadline(time.Time) error { return nil }
