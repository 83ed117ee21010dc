// fanout-listeners: many Listen streams in one process, counting events on command, in Go.
//
// The same program as `python -m bench.fanout_listeners`, with the same options and the same stdin
// protocol, for part (t) of the benchmark: it costs its machine 1–3 µs of CPU an event where the
// Python one costs more than the gateway it measures spends (40–70 µs against 25–40), so that on a
// machine with few cores the figure is the gateways' and not the listeners'. connection.go speaks HTTP/2 for the Listen
// calls; pacing.go reads every connection on one tick.
//
//	fanout-listeners --spread A1,A2 --streams 100 [--first 0] [--time-limit 300]
//
// opens 100 Listen streams on bench / value, stream k to address A[(first + k) mod len(A)] (at most
// streamsPerConnection a connection, each connection its own TCP connection), reads each up to its
// sync marker and prints "ready" on stdout. Then it obeys its stdin, one word a line: "start" zeroes
// the counts, "stop" prints {"events": E, "conflated": C, "ended": N} as one JSON line (events read
// since "start", intermediate values the gateways conflated away, streams that ended) and exits 0.
// It exits 1 at end of file on stdin, and after --time-limit seconds whatever happens, so that it
// never outlives the benchmark. A bad option exits 2.
package main

import (
	"bufio"
	"context"
	"errors"
	"flag"
	"fmt"
	"io"
	"net"
	"os"
	"runtime"
	"strconv"
	"strings"
	"sync/atomic"
	"time"

	"google.golang.org/protobuf/proto"

	pb "propertyservice/v1"
)

const (
	// The service and property of bench/target.py (SERVICE, VALUE_PROPERTY).
	service  = "bench"
	property = "value"
	// Listen streams one connection carries, as in part (c) and bench/fanout_listeners.py.
	streamsPerConnection = 25
	// How often every connection is read (pacing.go).
	readTick = 5 * time.Millisecond
	// Time the streams get to reach their sync markers.
	syncTimeout = 60 * time.Second
	// The longest command line read from stdin (the Python listeners' StreamReader limit).
	maxCommandLine = 1024
	exitOK         = 0
	exitFailed     = 1
	exitUsage      = 2
)

// counts are the events read by every stream of this process; zeroed by "start".
type counts struct {
	events    atomic.Int64
	conflated atomic.Int64
	ended     atomic.Int64
}

// listen opens the streams, then counts between "start" and "stop"; the exit code.
func listen(ctx context.Context, spread []string, streams, first int, commands io.Reader) (int, error) {
	perAddress := make([]int, len(spread))
	for k := 0; k < streams; k++ {
		perAddress[((first+k)%len(spread)+len(spread))%len(spread)]++
	}
	request, err := proto.Marshal(&pb.ListenRequest{Service: service, Property: property})
	if err != nil {
		return exitFailed, err
	}
	reads := newPacer(readTick)
	totals := &counts{}
	synced := make(chan error, streams)
	var opened []net.Conn
	defer func() {
		for _, conn := range opened {
			conn.Close()
		}
	}()
	// Stream k goes to address (first + k) mod len(spread): each address's streams are counted
	// above, and carried streamsPerConnection a connection, each connection its own TCP connection.
	for index, address := range spread {
		for left := perAddress[index]; left > 0; left -= streamsPerConnection {
			c, conn, err := openConnection(ctx, reads, address, min(left, streamsPerConnection), request, totals, synced)
			if err != nil {
				return exitFailed, err
			}
			opened = append(opened, conn)
			go c.read()
		}
	}
	deadline := time.NewTimer(syncTimeout)
	defer deadline.Stop()
	for n := 0; n < streams; n++ {
		select {
		case err := <-synced:
			if err != nil {
				return exitFailed, err
			}
		case <-deadline.C:
			return exitFailed, fmt.Errorf("%d of %d streams reached their sync marker within %v", n, streams, syncTimeout)
		}
	}
	fmt.Println("ready")
	lines := bufio.NewScanner(commands)
	lines.Buffer(make([]byte, 0, 64), maxCommandLine)
	for lines.Scan() {
		switch strings.TrimSpace(lines.Text()) {
		case "start":
			totals.events.Store(0)
			totals.conflated.Store(0)
		case "stop":
			// Printed before the deferred closes end the streams, so that they do not count as ended.
			fmt.Printf("{\"events\": %d, \"conflated\": %d, \"ended\": %d}\n",
				totals.events.Load(), totals.conflated.Load(), totals.ended.Load())
			return exitOK, nil
		}
	}
	if err := lines.Err(); err != nil {
		return exitFailed, fmt.Errorf("reading commands: %v", err)
	}
	return exitFailed, nil // end of file before "stop": the benchmark went away
}

func min(a, b int) int {
	if a < b {
		return a
	}
	return b
}

func run() int {
	flags := flag.NewFlagSet("fanout-listeners", flag.ContinueOnError)
	spreadText := flags.String("spread", "", "gateway addresses, comma-separated")
	streams := flags.Int("streams", 0, "Listen streams to open")
	first := flags.Int("first", 0, "the first stream's turn in the spread")
	timeLimit := flags.Float64("time-limit", 300, "seconds before giving up")
	if err := flags.Parse(os.Args[1:]); err != nil {
		if errors.Is(err, flag.ErrHelp) {
			return exitOK
		}
		return exitUsage
	}
	var spread []string
	for _, address := range strings.Split(*spreadText, ",") {
		if address = strings.TrimSpace(address); address != "" {
			spread = append(spread, address)
		}
	}
	if len(spread) == 0 || *streams < 1 || !(*timeLimit > 0) || flags.NArg() > 0 {
		fmt.Fprintln(os.Stderr, "error: --spread needs an address, --streams and --time-limit must be positive")
		flags.Usage()
		return exitUsage
	}
	// One thread runs every goroutine: a connection's reading is a few microseconds a tick, and a
	// second thread would only add hand-offs between threads, each a context switch.
	if os.Getenv("GOMAXPROCS") == "" {
		runtime.GOMAXPROCS(1)
	}
	// The limit holds whatever the streams and stdin do: the process exits from here.
	time.AfterFunc(time.Duration(*timeLimit*float64(time.Second)), func() {
		fmt.Fprintf(os.Stderr, "error: gave up after %s s\n", strconv.FormatFloat(*timeLimit, 'g', -1, 64))
		os.Exit(exitFailed)
	})
	code, err := listen(context.Background(), spread, *streams, *first, os.Stdin)
	if err != nil {
		fmt.Fprintf(os.Stderr, "error: %v\n", err)
	}
	return code
}

func main() { os.Exit(run()) }
