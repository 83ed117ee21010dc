// Drives a gateway's Foxglove endpoint with the protocol's own client (@foxglove/ws-protocol) and
// prints what it saw as one JSON object. Usage:
//   node drive.js URL SUBPROTOCOL ROBOT [TOKEN]
// It lists the channels and services, subscribes to the robot's pose and speed, publishes a speed,
// calls the robot's behaviors.stop service and reads the speed parameter, then closes.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, subprotocol, robot, token] = process.argv.slice(2);
const SPEED = 0.7;
const report = { protocol: null, serverInfo: null, channels: [], services: [], messages: {}, statuses: [], serviceResponses: [], serviceFailures: [], parameters: null };
const headers = token ? { Authorization: `Bearer ${token}` } : {};
const ws = new WebSocket(url, [subprotocol], { headers });
const client = new FoxgloveClient({ ws });
const decoder = new TextDecoder();
const topicOf = new Map();

function finish(code) {
  process.stdout.write(JSON.stringify(report) + "\n");
  client.close();
  process.exit(code);
}
setTimeout(() => { report.timedOut = true; finish(0); }, 15000);

ws.on("unexpected-response", (_req, res) => {
  report.refused = res.statusCode;
  finish(0);
});
client.on("open", () => { report.protocol = ws.protocol; });
client.on("error", (err) => { report.error = String(err); });
client.on("serverInfo", (info) => { report.serverInfo = info; });
client.on("status", (status) => { report.statuses.push(status); });
client.on("advertiseServices", (services) => {
  report.services.push(...services.map((s) => ({ id: s.id, name: s.name, type: s.type })));
});
client.on("serviceCallResponse", (response) => {
  report.serviceResponses.push({ serviceId: response.serviceId, callId: response.callId, encoding: response.encoding, body: JSON.parse(decoder.decode(response.data)) });
});
client.on("serviceCallFailure", (failure) => { report.serviceFailures.push(failure); });
client.on("parameterValues", (values) => { report.parameters = values; });
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = topicOf.get(subscriptionId);
  (report.messages[topic] ??= []).push({ timestamp: String(timestamp), body: JSON.parse(decoder.decode(data)) });
});

client.on("advertise", (channels) => {
  report.channels.push(...channels.map((c) => ({ id: c.id, topic: c.topic, encoding: c.encoding, schemaName: c.schemaName, schemaEncoding: c.schemaEncoding, schema: JSON.parse(c.schema) })));
  const byTopic = new Map(channels.map((c) => [c.topic, c]));
  for (const topic of [`/${robot}/pose`, `/${robot}/speed`, "/scene"]) {
    const channel = byTopic.get(topic);
    if (channel) topicOf.set(client.subscribe(channel.id), topic);
  }
  // Publish once the current values have had time to arrive.
  setTimeout(() => {
    const channelId = client.advertise({ topic: `/${robot}/speed`, encoding: "json", schemaName: "propertyservice.Number" });
    client.sendMessage(channelId, new TextEncoder().encode(JSON.stringify({ value: SPEED })));
    client.getParameters([`/${robot}/speed`], "after-publish");
  }, 500);
  setTimeout(() => {
    const stop = report.services.find((s) => s.name === `/${robot}/behaviors/stop`);
    if (stop) {
      client.sendServiceCallRequest({ serviceId: stop.id, callId: 41, encoding: "json", data: new TextEncoder().encode("{}") });
    }
  }, 1000);
  setTimeout(() => finish(0), 2500);
});
