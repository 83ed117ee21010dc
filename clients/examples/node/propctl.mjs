#!/usr/bin/env node
// propctl: Get, Set, Listen and Session calls on a Property Service gateway.
//
// The contract is loaded at run time from protos/propertyservice/v1/property_service.proto,
// so this client always speaks the same v1 contract as the gateway. Every result is one
// JSON line on stdout; an error is one line "error: CODE: message" on stderr.
//
// Exit codes (as psctl): 0 ok, 1 the call failed, 2 usage, 3 the gateway cannot be reached.

import { readFileSync } from "node:fs";
import { fileURLToPath } from "node:url";
import path from "node:path";
import { parseArgs } from "node:util";
import * as grpc from "@grpc/grpc-js";
import * as protoLoader from "@grpc/proto-loader";

const PROTO = fileURLToPath(
  new URL("../../../protos/propertyservice/v1/property_service.proto", import.meta.url),
);
const DEFAULT_TARGET = process.env.PSCTL_TARGET || "127.0.0.1:50051";
const CALL_TIMEOUT_MS = 10_000;
const EXIT = { ok: 0, failed: 1, usage: 2, unreachable: 3 };
const CODE_NAMES = Object.fromEntries(Object.entries(grpc.status).map(([name, n]) => [n, name]));

const USAGE = `usage: node propctl.mjs [-t HOST:PORT] COMMAND ...

  get SERVICE PATH [-p NAME=VALUE ...]         read one property
  set SERVICE PATH VALUE [-p NAME=VALUE ...]   write one property (or call a functional one)
  listen SERVICE PATH [--count N] [--updates-only] [--marks]
                                               stream changes; --marks also prints sync/heartbeat
  session SERVICE:PATH ...                     Get each SERVICE:PATH as a tagged request (ids 1, 2, ...)
                                               over one Session stream; one line per reply

  -t, --target HOST:PORT   gateway address (default $PSCTL_TARGET or 127.0.0.1:50051)
  --ca FILE                PEM CA of the gateway's certificate; makes the channel TLS ($PSCTL_CA)
  --cert FILE, --key FILE  client certificate and key, for mutual TLS ($PSCTL_CERT, $PSCTL_KEY)
  --token TOKEN            sent as "authorization: Bearer TOKEN" on every call ($PSCTL_TOKEN)`;

class UsageError extends Error {}

// TLS when a CA or a client certificate is given; plaintext otherwise (a gateway on loopback).
function channelCredentials({ ca, cert, key }) {
  if (Boolean(cert) !== Boolean(key)) throw new UsageError("--cert needs --key, and --key needs --cert");
  if (!ca && !cert) return grpc.credentials.createInsecure();
  const read = (file, flag) => {
    try {
      return readFileSync(file);
    } catch (error) {
      throw new UsageError(`${flag}: cannot read ${file}: ${error.code}`);
    }
  };
  return grpc.credentials.createSsl(
    ca ? read(ca, "--ca") : null,
    key ? read(key, "--key") : null,
    cert ? read(cert, "--cert") : null,
  );
}

// The bearer token goes as metadata on every call, unary and streamed alike.
function tokenInterceptor(token) {
  return (options, nextCall) =>
    new grpc.InterceptingCall(nextCall(options), {
      start(metadata, listener, next) {
        metadata.set("authorization", `Bearer ${token}`);
        next(metadata, listener);
      },
    });
}

function loadStub(target, security) {
  const definition = protoLoader.loadSync(PROTO, {
    keepCase: true,
    longs: Number, // sequence numbers and timestamp seconds fit a double for centuries
    enums: String,
    defaults: true,
    oneofs: true,
    includeDirs: [path.resolve(path.dirname(PROTO), "../../")],
  });
  const { PropertyService } = grpc.loadPackageDefinition(definition).propertyservice.v1;
  const interceptors = security.token ? [tokenInterceptor(security.token)] : [];
  return new PropertyService(target, channelCredentials(security), { interceptors });
}

function parseParameters(pairs = []) {
  const parameters = {};
  for (const pair of pairs) {
    const eq = pair.indexOf("=");
    if (eq <= 0) throw new UsageError(`parameter "${pair}" is not NAME=VALUE`);
    parameters[pair.slice(0, eq)] = pair.slice(eq + 1);
  }
  return parameters;
}

function parseRef(text) {
  const colon = text.indexOf(":");
  if (colon <= 0 || colon === text.length - 1) throw new UsageError(`"${text}" is not SERVICE:PATH`);
  return { service: text.slice(0, colon), property: text.slice(colon + 1) };
}

function deadline() {
  return new Date(Date.now() + CALL_TIMEOUT_MS);
}

function print(obj) {
  process.stdout.write(JSON.stringify(obj) + "\n");
}

function isoTime(ts) {
  if (!ts) return null;
  return new Date(ts.seconds * 1000 + Math.floor(ts.nanos / 1e6)).toISOString();
}

function eventJson(e) {
  return {
    service: e.service,
    property: e.property,
    value: e.value,
    sequence: e.sequence,
    time: isoTime(e.time),
    conflated: e.conflated,
    gap: e.gap,
    removed: e.removed,
  };
}

function unary(stub, method, request) {
  return new Promise((resolve, reject) => {
    stub[method](request, { deadline: deadline() }, (err, reply) => (err ? reject(err) : resolve(reply)));
  });
}

async function get(stub, [service, property], values) {
  const reply = await unary(stub, "Get", { service, property, parameters: parseParameters(values.param) });
  print({ service, property, value: reply.value });
}

async function set(stub, [service, property, value], values) {
  const request = { service, property, value, parameters: parseParameters(values.param) };
  const reply = await unary(stub, "Set", request);
  print({ service, property, value: reply.value });
}

function listen(stub, [service, property], values) {
  const count = values.count === undefined ? Infinity : Number(values.count);
  if (!(count === Infinity || (Number.isInteger(count) && count > 0))) {
    throw new UsageError("--count wants a positive integer");
  }
  const request = { service, property, options: { updates_only: Boolean(values["updates-only"]) } };
  return new Promise((resolve, reject) => {
    const call = stub.Listen(request);
    let seen = 0;
    let done = false;
    const stop = () => {
      done = true;
      call.cancel();
      resolve();
    };
    process.once("SIGINT", stop);
    call.on("data", (response) => {
      if (done) return;
      if (values.marks && response.sync) print({ sync: true });
      if (values.marks && response.heartbeat) print({ heartbeat: true });
      for (const event of response.events) {
        print(eventJson(event));
        if (++seen >= count) return stop();
      }
    });
    call.on("error", (err) => (done ? undefined : reject(err)));
    call.on("end", () => (done ? undefined : resolve()));
  });
}

function session(stub, refs) {
  if (refs.length === 0) throw new UsageError("session wants at least one SERVICE:PATH");
  const requests = refs.map((text, i) => ({ id: i + 1, get: parseRef(text) }));
  return new Promise((resolve, reject) => {
    const call = stub.Session({ deadline: deadline() });
    const pending = new Set(requests.map((r) => r.id));
    let failed = false;
    call.on("data", (response) => {
      for (const reply of response.replies) {
        const code = reply.status ? reply.status.code : 0;
        const line = { id: reply.id, code: CODE_NAMES[code] ?? String(code) };
        if (code === 0) line.value = reply.get.value;
        else line.message = reply.status.message;
        failed ||= code !== 0;
        print(line);
        pending.delete(reply.id);
      }
      if (pending.size === 0) call.end(); // every Get answered: half-close, the gateway ends the stream
    });
    call.on("error", reject);
    call.on("end", () => {
      if (pending.size > 0) reject(new Error(`session ended without replies to ids ${[...pending]}`));
      else resolve(failed ? EXIT.failed : EXIT.ok);
    });
    call.write({ requests });
  });
}

const COMMANDS = {
  get: { run: get, args: 2 },
  set: { run: set, args: 3 },
  listen: { run: listen, args: 2 },
  session: { run: session, args: -1 },
};

async function main(argv) {
  const { values, positionals } = parseArgs({
    args: argv,
    allowPositionals: true,
    options: {
      target: { type: "string", short: "t", default: DEFAULT_TARGET },
      param: { type: "string", short: "p", multiple: true },
      count: { type: "string" },
      "updates-only": { type: "boolean" },
      marks: { type: "boolean" },
      help: { type: "boolean", short: "h" },
      ca: { type: "string", default: process.env.PSCTL_CA || "" },
      cert: { type: "string", default: process.env.PSCTL_CERT || "" },
      key: { type: "string", default: process.env.PSCTL_KEY || "" },
      token: { type: "string", default: process.env.PSCTL_TOKEN || "" },
    },
  });
  if (values.help) {
    console.log(USAGE);
    return EXIT.ok;
  }
  const [name, ...args] = positionals;
  const command = COMMANDS[name];
  if (!command) throw new UsageError(name ? `unknown command "${name}"` : "no command given");
  if (command.args >= 0 && args.length !== command.args) {
    throw new UsageError(`${name} wants ${command.args} arguments, got ${args.length}`);
  }
  const stub = loadStub(values.target, values);
  try {
    return (await command.run(stub, args, values)) ?? EXIT.ok;
  } finally {
    stub.close();
  }
}

try {
  process.exitCode = await main(process.argv.slice(2));
} catch (err) {
  if (err instanceof UsageError || String(err.code).startsWith("ERR_PARSE_ARGS")) {
    console.error(`error: ${err.message}\n\n${USAGE}`);
    process.exitCode = EXIT.usage;
  } else if (typeof err.code === "number") {
    // A gRPC status: name the code, as grpcurl and psctl do.
    console.error(`error: ${CODE_NAMES[err.code] ?? err.code}: ${err.details}`);
    process.exitCode = err.code === grpc.status.UNAVAILABLE ? EXIT.unreachable : EXIT.failed;
  } else {
    console.error(`error: ${err.message}`);
    process.exitCode = EXIT.failed;
  }
}
