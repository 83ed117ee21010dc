package main

// One HTTP/2 connection carrying up to streamsPerConnection Listen calls, spoken with
// golang.org/x/net/http2's framer: gRPC's framing of one server-streaming call (HEADERS, one request
// message, then response messages and trailers) is all these listeners need. grpc-go gives each
// stream a goroutine of its own, hands it every message through a buffer and a channel, and decodes
// every event into objects; on a busy two-core machine that cost 8–15 µs an event, a quarter or
// more of what the gateway spends producing it (docs/performance.md, part (t)). Here one goroutine
// reads a connection's frames and scans each message where it lies in the read buffer, counting its
// events and their conflated values without a copy or an object.

import (
	"bufio"
	"bytes"
	"context"
	"encoding/binary"
	"errors"
	"fmt"
	"net"

	"golang.org/x/net/http2"
	"golang.org/x/net/http2/hpack"
	"google.golang.org/protobuf/encoding/protowire"
	"google.golang.org/protobuf/proto"
	"google.golang.org/protobuf/reflect/protoreflect"

	pb "propertyservice/v1"
)

const (
	listenPath = "/propertyservice.v1.PropertyService/Listen"
	// The flow-control window granted to the gateway on each stream and on the connection: so
	// large that it never waits for these listeners in a run. It is topped up (WINDOW_UPDATE) once
	// half of it is used.
	window = 1 << 30
	// HTTP/2's initial connection window (RFC 9113 §6.9.2), whatever the settings say.
	initialConnectionWindow = 65535
	// The largest message accepted, grpc's default receive limit; the gateway's are a few hundred
	// bytes.
	maxMessage = 4 << 20
	// Bytes read from the socket at a time: what a tick brings on a busy connection.
	readBuffer = 64 << 10
	// The largest header list accepted (trailers carry a status message).
	maxHeaderList = 64 << 10
)

// The field numbers the scan reads, taken from the generated descriptors so that they follow the
// .proto: ListenResponse.events, ListenResponse.sync and Event.conflated.
var (
	eventsField    = fieldNumber(&pb.ListenResponse{}, "events")
	syncField      = fieldNumber(&pb.ListenResponse{}, "sync")
	conflatedField = fieldNumber(&pb.Event{}, "conflated")
)

func fieldNumber(message proto.Message, name string) protowire.Number {
	field := message.ProtoReflect().Descriptor().Fields().ByName(protoreflect.Name(name))
	if field == nil {
		panic(fmt.Sprintf("%T has no field %q", message, name))
	}
	return field.Number()
}

// listenStream is one Listen call on a connection.
type listenStream struct {
	id      uint32
	synced  bool
	pending []byte // the part of a message that came in an earlier DATA frame
	unacked uint32 // bytes received since the last WINDOW_UPDATE for the stream
}

// connection reads its streams' frames on one goroutine (read); until then only its opener writes.
type connection struct {
	framer  *http2.Framer
	out     *bufio.Writer
	streams map[uint32]*listenStream
	unacked uint32 // bytes received since the last WINDOW_UPDATE for the connection
	totals  *counts
	synced  chan<- error
}

// openConnection dials address through reads and starts `streams` Listen calls carrying request
// (a serialized ListenRequest). Each stream sends one value on synced: nil at its sync marker, or
// why it ended before it.
func openConnection(ctx context.Context, reads *pacer, address string, streams int, request []byte,
	totals *counts, synced chan<- error) (*connection, net.Conn, error) {
	conn, err := reads.dial(ctx, address)
	if err != nil {
		return nil, nil, err
	}
	out := bufio.NewWriter(conn)
	framer := http2.NewFramer(out, bufio.NewReaderSize(conn, readBuffer))
	framer.ReadMetaHeaders = hpack.NewDecoder(4096, nil)
	framer.MaxHeaderListSize = maxHeaderList
	c := &connection{framer: framer, out: out, streams: make(map[uint32]*listenStream, streams),
		totals: totals, synced: synced}
	message := make([]byte, 5+len(request)) // gRPC's framing: not compressed, a 4-byte length
	binary.BigEndian.PutUint32(message[1:5], uint32(len(request)))
	copy(message[5:], request)
	var block bytes.Buffer
	headers := hpack.NewEncoder(&block)
	_, err = out.WriteString(http2.ClientPreface)
	if err == nil {
		err = framer.WriteSettings(http2.Setting{ID: http2.SettingEnablePush, Val: 0},
			http2.Setting{ID: http2.SettingInitialWindowSize, Val: window})
	}
	if err == nil {
		err = framer.WriteWindowUpdate(0, window-initialConnectionWindow)
	}
	for n := 0; n < streams && err == nil; n++ {
		id := uint32(2*n + 1) // a client's streams have odd ids, in increasing order
		block.Reset()
		for _, field := range []hpack.HeaderField{
			{Name: ":method", Value: "POST"}, {Name: ":scheme", Value: "http"},
			{Name: ":path", Value: listenPath}, {Name: ":authority", Value: address},
			{Name: "content-type", Value: "application/grpc"}, {Name: "te", Value: "trailers"},
		} {
			if err = headers.WriteField(field); err != nil {
				break
			}
		}
		if err == nil {
			err = framer.WriteHeaders(http2.HeadersFrameParam{StreamID: id, BlockFragment: block.Bytes(), EndHeaders: true})
		}
		if err == nil {
			err = framer.WriteData(id, true, message)
		}
		c.streams[id] = &listenStream{id: id}
	}
	if err == nil {
		err = out.Flush()
	}
	if err != nil {
		conn.Close()
		return nil, nil, fmt.Errorf("opening Listen streams on %s: %v", address, err)
	}
	return c, conn, nil
}

// read reads frames until the connection ends; then every stream still open has ended with it.
func (c *connection) read() {
	err := c.readFrames()
	for _, s := range c.streams {
		c.end(s, fmt.Errorf("the connection ended: %v", err))
	}
}

func (c *connection) readFrames() error {
	for {
		frame, err := c.framer.ReadFrame()
		if err != nil {
			return err
		}
		switch f := frame.(type) {
		case *http2.DataFrame:
			s := c.streams[f.StreamID]
			if s != nil {
				if err := c.data(s, f.Data()); err != nil {
					return err
				}
				if f.StreamEnded() {
					c.end(s, errors.New("the stream ended without trailers"))
				}
			}
			if err := c.acknowledge(s, f.Length); err != nil {
				return err
			}
		case *http2.MetaHeadersFrame: // the response headers; trailers when they end the stream
			if s := c.streams[f.StreamID]; s != nil && f.StreamEnded() {
				c.end(s, callStatus(f))
			}
		case *http2.RSTStreamFrame:
			if s := c.streams[f.StreamID]; s != nil {
				c.end(s, fmt.Errorf("the gateway reset the stream (%v)", f.ErrCode))
			}
		case *http2.SettingsFrame:
			if !f.IsAck() {
				if err := c.send(c.framer.WriteSettingsAck()); err != nil {
					return err
				}
			}
		case *http2.PingFrame:
			if !f.IsAck() {
				if err := c.send(c.framer.WritePing(true, f.Data)); err != nil {
					return err
				}
			}
		}
		// WINDOW_UPDATE: nothing more is sent; GOAWAY: the streams it spares go on until they end.
	}
}

// send flushes what a framer call wrote, unless it failed.
func (c *connection) send(written error) error {
	if written != nil {
		return written
	}
	return c.out.Flush()
}

// acknowledge counts n bytes received on s (nil: a stream already ended) and on the connection, and
// tops up a window once half of it is used.
func (c *connection) acknowledge(s *listenStream, n uint32) error {
	c.unacked += n
	if c.unacked >= window/2 {
		if err := c.send(c.framer.WriteWindowUpdate(0, c.unacked)); err != nil {
			return err
		}
		c.unacked = 0
	}
	if s == nil {
		return nil
	}
	s.unacked += n
	if s.unacked >= window/2 {
		if err := c.send(c.framer.WriteWindowUpdate(s.id, s.unacked)); err != nil {
			return err
		}
		s.unacked = 0
	}
	return nil
}

// data takes in one DATA frame's payload: every message it completes is counted, the rest waits.
func (c *connection) data(s *listenStream, payload []byte) error {
	p := payload
	if len(s.pending) > 0 {
		s.pending = append(s.pending, payload...)
		p = s.pending
	}
	for len(p) >= 5 {
		if p[0] != 0 {
			return errors.New("the gateway sent a compressed message, which was not asked for")
		}
		size := binary.BigEndian.Uint32(p[1:5])
		if size > maxMessage {
			return fmt.Errorf("the gateway sent a message of %d bytes, more than %d", size, maxMessage)
		}
		if uint32(len(p)-5) < size {
			break
		}
		if err := c.message(s, p[5:5+size]); err != nil {
			return err
		}
		p = p[5+size:]
	}
	// What is left is shorter than its message (at most maxMessage and its prefix); append copies
	// it, within pending or out of the frame, which the framer reuses.
	s.pending = append(s.pending[:0], p...)
	return nil
}

// message scans one ListenResponse: before the stream's sync marker it waits for the marker (the
// current values are not counted, as the Python listeners do not count them), after it counts.
func (c *connection) message(s *listenStream, m []byte) error {
	var events, conflated int64
	sync := false
	for len(m) > 0 {
		number, kind, n := protowire.ConsumeTag(m)
		if n < 0 {
			return fmt.Errorf("a malformed ListenResponse: %v", protowire.ParseError(n))
		}
		m = m[n:]
		switch {
		case number == eventsField && kind == protowire.BytesType:
			event, n := protowire.ConsumeBytes(m)
			if n < 0 {
				return fmt.Errorf("a malformed event: %v", protowire.ParseError(n))
			}
			m = m[n:]
			count, err := conflatedOf(event)
			if err != nil {
				return err
			}
			events++
			conflated += count
		case number == syncField && kind == protowire.VarintType:
			value, n := protowire.ConsumeVarint(m)
			if n < 0 {
				return fmt.Errorf("a malformed sync marker: %v", protowire.ParseError(n))
			}
			m = m[n:]
			sync = value != 0
		default:
			n := protowire.ConsumeFieldValue(number, kind, m)
			if n < 0 {
				return fmt.Errorf("a malformed ListenResponse: %v", protowire.ParseError(n))
			}
			m = m[n:]
		}
	}
	if !s.synced {
		if sync {
			s.synced = true
			c.synced <- nil
		}
		return nil
	}
	if events > 0 {
		c.totals.events.Add(events)
		c.totals.conflated.Add(conflated)
	}
	return nil
}

// conflatedOf reads an Event's conflated count.
func conflatedOf(event []byte) (int64, error) {
	var conflated int64
	for len(event) > 0 {
		number, kind, n := protowire.ConsumeTag(event)
		if n < 0 {
			return 0, fmt.Errorf("a malformed event: %v", protowire.ParseError(n))
		}
		event = event[n:]
		if number == conflatedField && kind == protowire.VarintType {
			value, n := protowire.ConsumeVarint(event)
			if n < 0 {
				return 0, fmt.Errorf("a malformed event: %v", protowire.ParseError(n))
			}
			event = event[n:]
			conflated = int64(value)
			continue
		}
		n = protowire.ConsumeFieldValue(number, kind, event)
		if n < 0 {
			return 0, fmt.Errorf("a malformed event: %v", protowire.ParseError(n))
		}
		event = event[n:]
	}
	return conflated, nil
}

// end takes s off the connection: ended when it had synced, else why it never did goes to synced.
func (c *connection) end(s *listenStream, why error) {
	delete(c.streams, s.id)
	if !s.synced {
		c.synced <- fmt.Errorf("a Listen stream ended before its sync marker: %v", why)
		return
	}
	c.totals.ended.Add(1)
}

// callStatus is the status a stream's trailers carry (grpc-status and grpc-message).
func callStatus(trailers *http2.MetaHeadersFrame) error {
	code, message := "", ""
	for _, field := range trailers.Fields {
		switch field.Name {
		case "grpc-status":
			code = field.Value
		case "grpc-message":
			message = field.Value
		}
	}
	switch {
	case code == "":
		return fmt.Errorf("the stream ended without a grpc-status (HTTP status %q)", trailers.PseudoValue("status"))
	case message == "":
		return fmt.Errorf("grpc-status %s", code)
	}
	return fmt.Errorf("grpc-status %s: %s", code, message)
}
