// propctl: Get, Set, Listen and Session calls on a Property Service gateway, in C++.
//
// The stubs come from protos/propertyservice/v1/property_service.proto through protoc and
// grpc_cpp_plugin (CMakeLists.txt makes them); the gRPC stack is gRPC C++. Every result is one
// JSON line on stdout; an error is one line "error: CODE: message" on stderr.
//
// Exit codes (as psctl and the Node.js client): 0 ok, 1 the call failed, 2 usage, 3 the gateway
// cannot be reached.
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <grpcpp/grpcpp.h>

#include "propertyservice/v1/property_service.grpc.pb.h"

namespace pb = propertyservice::v1;

namespace {

constexpr const char* kDefaultTarget = "127.0.0.1:50051";
constexpr auto kCallTimeout = std::chrono::seconds(10);
// A Listen ends at the sync marker; a stream that sends more than this many events before it is
// cut short, so that a wildcard over a large tree cannot keep the client printing forever.
constexpr std::size_t kMaxEventsBeforeSync = 10000;
enum Exit { kOk = 0, kFailed = 1, kUsage = 2, kUnreachable = 3 };

constexpr const char* kUsageText =
    "usage: propctl [-t HOST:PORT] COMMAND ...\n"
    "\n"
    "  get SERVICE PATH              read one property\n"
    "  set SERVICE PATH VALUE        write one property (or call a functional one)\n"
    "  listen SERVICE PATH           print the current values, then {\"sync\":true}, then end\n"
    "  session SERVICE:PATH ...      Get each SERVICE:PATH as a tagged request (ids 1, 2, ...)\n"
    "                                over one Session stream; one line per reply\n"
    "\n"
    "  -t HOST:PORT   gateway address (default $PSCTL_TARGET or 127.0.0.1:50051)\n";

struct UsageError {
  std::string message;
};

// The names of google.rpc.Code, as the gateway's documentation spells them.
const char* CodeName(int code) {
  static const char* const kNames[] = {
      "OK",           "CANCELLED",          "UNKNOWN",           "INVALID_ARGUMENT",
      "DEADLINE_EXCEEDED", "NOT_FOUND",     "ALREADY_EXISTS",    "PERMISSION_DENIED",
      "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "ABORTED",    "OUT_OF_RANGE",
      "UNIMPLEMENTED", "INTERNAL",          "UNAVAILABLE",       "DATA_LOSS",
      "UNAUTHENTICATED"};
  return code >= 0 && code <= 16 ? kNames[code] : "UNKNOWN";
}

// A JSON string literal: quotes, backslashes and control characters escaped; other bytes kept
// (values are UTF-8 text).
std::string Json(const std::string& text) {
  std::string out = "\"";
  for (unsigned char c : text) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      default:
        if (c < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", c);
          out += buf;
        } else {
          out += static_cast<char>(c);
        }
    }
  }
  return out + "\"";
}

std::string Bool(bool b) { return b ? "true" : "false"; }

void Deadline(grpc::ClientContext& context) {
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
}

grpc::Status Get(pb::PropertyService::Stub& stub, const std::vector<std::string>& args, int& exit) {
  if (args.size() != 2) throw UsageError{"get takes SERVICE PATH"};
  grpc::ClientContext context;
  Deadline(context);
  pb::GetRequest request;
  request.set_service(args[0]);
  request.set_property(args[1]);
  pb::GetResponse reply;
  grpc::Status status = stub.Get(&context, request, &reply);
  if (status.ok()) {
    std::cout << "{\"service\":" << Json(args[0]) << ",\"property\":" << Json(args[1])
              << ",\"value\":" << Json(reply.value()) << "}" << std::endl;
    exit = kOk;
  }
  return status;
}

grpc::Status Set(pb::PropertyService::Stub& stub, const std::vector<std::string>& args, int& exit) {
  if (args.size() != 3) throw UsageError{"set takes SERVICE PATH VALUE"};
  grpc::ClientContext context;
  Deadline(context);
  pb::SetRequest request;
  request.set_service(args[0]);
  request.set_property(args[1]);
  request.set_value(args[2]);
  pb::SetResponse reply;
  grpc::Status status = stub.Set(&context, request, &reply);
  if (status.ok()) {
    std::cout << "{\"service\":" << Json(args[0]) << ",\"property\":" << Json(args[1])
              << ",\"value\":" << Json(reply.value()) << "}" << std::endl;
    exit = kOk;
  }
  return status;
}

grpc::Status Listen(pb::PropertyService::Stub& stub, const std::vector<std::string>& args, int& exit) {
  if (args.size() != 2) throw UsageError{"listen takes SERVICE PATH"};
  grpc::ClientContext context;
  Deadline(context);
  pb::ListenRequest request;
  request.set_service(args[0]);
  request.set_property(args[1]);
  std::unique_ptr<grpc::ClientReader<pb::ListenResponse>> stream = stub.Listen(&context, request);
  pb::ListenResponse message;
  std::size_t seen = 0;
  while (stream->Read(&message)) {
    for (const pb::Event& e : message.events()) {
      if (++seen > kMaxEventsBeforeSync) {
        context.TryCancel();
        stream->Finish();
        return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                            "more than " + std::to_string(kMaxEventsBeforeSync) +
                                " events before the sync marker");
      }
      std::cout << "{\"service\":" << Json(e.service()) << ",\"property\":" << Json(e.property())
                << ",\"value\":" << Json(e.value()) << ",\"sequence\":" << e.sequence()
                << ",\"conflated\":" << e.conflated() << ",\"gap\":" << Bool(e.gap())
                << ",\"removed\":" << Bool(e.removed()) << "}" << std::endl;
    }
    if (message.sync()) {
      std::cout << "{\"sync\":true}" << std::endl;
      context.TryCancel();  // ends the stream on the gateway; Finish then reports CANCELLED
      stream->Finish();
      exit = kOk;
      return grpc::Status::OK;
    }
  }
  grpc::Status status = stream->Finish();
  if (status.ok()) {
    return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the stream ended before the sync marker");
  }
  return status;
}

grpc::Status Session(pb::PropertyService::Stub& stub, const std::vector<std::string>& args, int& exit) {
  if (args.empty()) throw UsageError{"session takes one or more SERVICE:PATH"};
  pb::SessionRequest batch;
  std::uint64_t id = 0;
  for (const std::string& arg : args) {
    std::size_t colon = arg.find(':');
    if (colon == std::string::npos || colon == 0 || colon + 1 == arg.size()) {
      throw UsageError{"session: \"" + arg + "\" is not SERVICE:PATH"};
    }
    pb::Request* request = batch.add_requests();
    request->set_id(++id);
    request->mutable_get()->set_service(arg.substr(0, colon));
    request->mutable_get()->set_property(arg.substr(colon + 1));
  }
  grpc::ClientContext context;
  Deadline(context);
  auto stream = stub.Session(&context);
  if (!stream->Write(batch)) return stream->Finish();
  // Every Get gets exactly one reply; once all are in, closing our side ends the stream.
  std::size_t pending = args.size();
  exit = kOk;
  pb::SessionResponse message;
  while (pending > 0 && stream->Read(&message)) {
    for (const pb::Reply& r : message.replies()) {
      --pending;
      if (r.status().code() == 0) {
        std::cout << "{\"id\":" << r.id() << ",\"code\":\"OK\",\"value\":" << Json(r.get().value())
                  << "}" << std::endl;
      } else {
        exit = kFailed;
        std::cout << "{\"id\":" << r.id() << ",\"code\":\"" << CodeName(r.status().code())
                  << "\",\"message\":" << Json(r.status().message()) << "}" << std::endl;
      }
    }
  }
  stream->WritesDone();
  grpc::Status status = stream->Finish();
  if (status.ok() && pending > 0) {
    return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                        "the session ended with " + std::to_string(pending) + " replies missing");
  }
  return status;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> args(argv + 1, argv + argc);
  const char* env_target = std::getenv("PSCTL_TARGET");
  std::string target = env_target != nullptr && *env_target ? env_target : kDefaultTarget;
  if (args.size() >= 2 && (args[0] == "-t" || args[0] == "--target")) {
    target = args[1];
    args.erase(args.begin(), args.begin() + 2);
  }
  using Command = grpc::Status (*)(pb::PropertyService::Stub&, const std::vector<std::string>&, int&);
  const std::map<std::string, Command> commands = {
      {"get", Get}, {"set", Set}, {"listen", Listen}, {"session", Session}};
  if (args.empty()) {
    std::cerr << kUsageText;
    return kUsage;
  }
  if (args[0] == "-h" || args[0] == "--help") {
    std::cout << kUsageText;
    return 0;
  }
  auto found = commands.find(args[0]);
  if (found == commands.end()) {
    std::cerr << "error: unknown command \"" << args[0] << "\"\n" << kUsageText;
    return kUsage;
  }
  auto channel = grpc::CreateChannel(target, grpc::InsecureChannelCredentials());
  auto stub = pb::PropertyService::NewStub(channel);
  int exit = kFailed;
  grpc::Status status;
  try {
    status = found->second(*stub, std::vector<std::string>(args.begin() + 1, args.end()), exit);
  } catch (const UsageError& bad) {
    std::cerr << "error: " << bad.message << "\n" << kUsageText;
    return kUsage;
  }
  if (!status.ok()) {
    std::cerr << "error: " << CodeName(status.error_code()) << ": " << status.error_message()
              << std::endl;
    return status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                   status.error_code() == grpc::StatusCode::UNAUTHENTICATED
               ? kUnreachable
               : kFailed;
  }
  return exit;
}
