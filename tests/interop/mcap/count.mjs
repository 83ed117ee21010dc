// Reads MCAP files with the format's own TypeScript reader (@mcap/core), through their summary and
// chunk indexes, and prints what each holds as JSON: per-topic message counts, each channel's schema
// and encodings, the metadata record names and the writing library.
// Usage: node count.mjs FILE...
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { decompress } from "fzstd";

const decompressHandlers = {
  zstd: (data, size) => decompress(data, new Uint8Array(Number(size))),
};

async function read(path) {
  const handle = await open(path, "r");
  try {
    const readable = {
      size: async () => BigInt((await handle.stat()).size),
      read: async (offset, length) => {
        const buffer = new Uint8Array(Number(length));
        await handle.read(buffer, 0, Number(length), Number(offset));
        return buffer;
      },
    };
    const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
    const topics = {};
    const channels = {};
    for (const channel of reader.channelsById.values()) {
      const schema = reader.schemasById.get(channel.schemaId);
      channels[channel.topic] = {
        messageEncoding: channel.messageEncoding,
        schema: schema ? schema.name : "",
        schemaEncoding: schema ? schema.encoding : "",
      };
    }
    for await (const message of reader.readMessages()) {
      const topic = reader.channelsById.get(message.channelId).topic;
      topics[topic] = (topics[topic] ?? 0) + 1;
    }
    const metadata = [];
    for await (const record of reader.readMetadata()) {
      metadata.push(record.name);
    }
    return { library: reader.header.library, topics, channels, metadata };
  } finally {
    await handle.close();
  }
}

const report = {};
for (const path of process.argv.slice(2)) {
  report[path] = await read(path);
}
process.stdout.write(JSON.stringify(report));
