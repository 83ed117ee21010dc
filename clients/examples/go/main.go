// propctl: Get, Set, Listen and Session calls on a Property Service gateway, in Go.
//
// The stubs come from protos/propertyservice/v1/property_service.proto through protoc-gen-go and
// protoc-gen-go-grpc (build.sh makes them); the gRPC stack is grpc-go. Every result is one JSON line
// on stdout; an error is one line "error: CODE: message" on stderr.
//
// Exit codes (as psctl and the Node.js client): 0 ok, 1 the call failed, 2 usage, 3 the gateway
// cannot be reached.
package main

import (
	"context"
	"encoding/json"
	"errors"
	"flag"
	"fmt"
	"io"
	"os"
	"strings"
	"time"

	"google.golang.org/grpc"
	"google.golang.org/grpc/codes"
	"google.golang.org/grpc/status"

	pb "propertyservice/v1"
)

const (
	defaultTarget = "127.0.0.1:50051"
	callTimeout   = 10 * time.Second
	// A Listen ends at the sync marker; a stream that sends more than this many events before it
	// is cut short, so that a wildcard over a large tree cannot keep the client printing forever.
	maxEventsBeforeSync = 10000
	exitOK              = 0
	exitFailed          = 1
	exitUsage           = 2
	exitUnreachable     = 3
)

const usage = `usage: propctl [-t HOST:PORT] COMMAND ...

  get SERVICE PATH              read one property
  set SERVICE PATH VALUE        write one property (or call a functional one)
  listen SERVICE PATH           print the current values, then {"sync":true}, then end
  session SERVICE:PATH ...      Get each SERVICE:PATH as a tagged request (ids 1, 2, ...)
                                over one Session stream; one line per reply

  -t HOST:PORT   gateway address (default $PSCTL_TARGET or 127.0.0.1:50051)
`

// The lines printed, their keys in the order the other clients print them.
type valueLine struct {
	Service  string `json:"service"`
	Property string `json:"property"`
	Value    string `json:"value"`
}

type eventLine struct {
	Service   string `json:"service"`
	Property  string `json:"property"`
	Value     string `json:"value"`
	Sequence  uint64 `json:"sequence"`
	Conflated uint32 `json:"conflated"`
	Gap       bool   `json:"gap"`
	Removed   bool   `json:"removed"`
}

type syncLine struct {
	Sync bool `json:"sync"`
}

type replyLine struct {
	ID      uint64  `json:"id"`
	Code    string  `json:"code"`
	Value   *string `json:"value,omitempty"`
	Message *string `json:"message,omitempty"`
}

type usageError struct{ msg string }

func (e usageError) Error() string { return e.msg }

// printJSON prints one line; markers keep their "<" and ">" (no HTML escaping), as the other
// clients print them.
func printJSON(v any) {
	out := json.NewEncoder(os.Stdout)
	out.SetEscapeHTML(false)
	if err := out.Encode(v); err != nil {
		panic(err) // only the line structs above, of strings, numbers and booleans, are printed
	}
}

func get(ctx context.Context, client pb.PropertyServiceClient, args []string) (int, error) {
	if len(args) != 2 {
		return 0, usageError{"get takes SERVICE PATH"}
	}
	reply, err := client.Get(ctx, &pb.GetRequest{Service: args[0], Property: args[1]})
	if err != nil {
		return 0, err
	}
	printJSON(valueLine{args[0], args[1], reply.GetValue()})
	return exitOK, nil
}

func set(ctx context.Context, client pb.PropertyServiceClient, args []string) (int, error) {
	if len(args) != 3 {
		return 0, usageError{"set takes SERVICE PATH VALUE"}
	}
	reply, err := client.Set(ctx, &pb.SetRequest{Service: args[0], Property: args[1], Value: args[2]})
	if err != nil {
		return 0, err
	}
	printJSON(valueLine{args[0], args[1], reply.GetValue()})
	return exitOK, nil
}

func listen(ctx context.Context, client pb.PropertyServiceClient, args []string) (int, error) {
	if len(args) != 2 {
		return 0, usageError{"listen takes SERVICE PATH"}
	}
	ctx, cancel := context.WithCancel(ctx)
	defer cancel() // ends the stream on the gateway once the sync marker is in
	stream, err := client.Listen(ctx, &pb.ListenRequest{Service: args[0], Property: args[1]})
	if err != nil {
		return 0, err
	}
	seen := 0
	for {
		msg, err := stream.Recv()
		if err != nil {
			if errors.Is(err, io.EOF) {
				return 0, status.Error(codes.Unavailable, "the stream ended before the sync marker")
			}
			return 0, err
		}
		for _, e := range msg.GetEvents() {
			seen++
			if seen > maxEventsBeforeSync {
				return 0, status.Errorf(codes.ResourceExhausted, "more than %d events before the sync marker", maxEventsBeforeSync)
			}
			printJSON(eventLine{
				e.GetService(), e.GetProperty(), e.GetValue(), e.GetSequence(), e.GetConflated(), e.GetGap(), e.GetRemoved(),
			})
		}
		if msg.GetSync() {
			printJSON(syncLine{true})
			return exitOK, nil
		}
	}
}

func session(ctx context.Context, client pb.PropertyServiceClient, args []string) (int, error) {
	if len(args) == 0 {
		return 0, usageError{"session takes one or more SERVICE:PATH"}
	}
	batch := &pb.SessionRequest{}
	for i, arg := range args {
		service, property, ok := strings.Cut(arg, ":")
		if !ok || service == "" || property == "" {
			return 0, usageError{fmt.Sprintf("session: %q is not SERVICE:PATH", arg)}
		}
		batch.Requests = append(batch.Requests, &pb.Request{
			Id:   uint64(i + 1),
			Call: &pb.Request_Get{Get: &pb.GetRequest{Service: service, Property: property}},
		})
	}
	stream, err := client.Session(ctx)
	if err != nil {
		return 0, err
	}
	if err := stream.Send(batch); err != nil {
		return 0, err
	}
	// Every Get gets exactly one reply; once all are in, closing our side ends the stream.
	code, pending := exitOK, len(args)
	for pending > 0 {
		msg, err := stream.Recv()
		if err != nil {
			if errors.Is(err, io.EOF) {
				return 0, status.Errorf(codes.Unavailable, "the session ended with %d replies missing", pending)
			}
			return 0, err
		}
		for _, r := range msg.GetReplies() {
			pending--
			c := codes.Code(r.GetStatus().GetCode())
			if c == codes.OK {
				value := r.GetGet().GetValue()
				printJSON(replyLine{ID: r.GetId(), Code: "OK", Value: &value})
			} else {
				code = exitFailed
				message := r.GetStatus().GetMessage()
				printJSON(replyLine{ID: r.GetId(), Code: codeName(c), Message: &message})
			}
		}
	}
	if err := stream.CloseSend(); err != nil {
		return 0, err
	}
	return code, nil
}

// codeNames spell the google.rpc.Code numbers as the gateway's documentation does: NOT_FOUND.
var codeNames = [...]string{
	"OK", "CANCELLED", "UNKNOWN", "INVALID_ARGUMENT", "DEADLINE_EXCEEDED", "NOT_FOUND",
	"ALREADY_EXISTS", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "ABORTED",
	"OUT_OF_RANGE", "UNIMPLEMENTED", "INTERNAL", "UNAVAILABLE", "DATA_LOSS", "UNAUTHENTICATED",
}

func codeName(c codes.Code) string {
	if int(c) < len(codeNames) {
		return codeNames[c]
	}
	return "UNKNOWN"
}

func run() int {
	flags := flag.NewFlagSet("propctl", flag.ContinueOnError)
	flags.SetOutput(io.Discard)
	target := os.Getenv("PSCTL_TARGET")
	if target == "" {
		target = defaultTarget
	}
	flags.StringVar(&target, "t", target, "gateway address")
	err := flags.Parse(os.Args[1:])
	if errors.Is(err, flag.ErrHelp) {
		fmt.Print(usage)
		return 0
	}
	if err != nil || flags.NArg() == 0 {
		fmt.Fprint(os.Stderr, usage)
		return exitUsage
	}
	commands := map[string]func(context.Context, pb.PropertyServiceClient, []string) (int, error){
		"get": get, "set": set, "listen": listen, "session": session,
	}
	command, ok := commands[flags.Arg(0)]
	if !ok {
		fmt.Fprintf(os.Stderr, "error: unknown command %q\n%s", flags.Arg(0), usage)
		return exitUsage
	}
	conn, err := grpc.Dial(target, grpc.WithInsecure())
	if err != nil {
		fmt.Fprintf(os.Stderr, "error: %v\n", err)
		return exitUsage
	}
	defer conn.Close()
	ctx, cancel := context.WithTimeout(context.Background(), callTimeout)
	defer cancel()
	code, err := command(ctx, pb.NewPropertyServiceClient(conn), flags.Args()[1:])
	var bad usageError
	switch {
	case errors.As(err, &bad):
		fmt.Fprintf(os.Stderr, "error: %s\n%s", bad.msg, usage)
		return exitUsage
	case err != nil:
		s := status.Convert(err)
		fmt.Fprintf(os.Stderr, "error: %s: %s\n", codeName(s.Code()), s.Message())
		if s.Code() == codes.Unavailable || s.Code() == codes.Unauthenticated {
			return exitUnreachable
		}
		return exitFailed
	}
	return code
}

func main() { os.Exit(run()) }
