// Decodes every message of MCAP files with Foxglove's readers (@mcap/core, @foxglove/rosmsg,
// @foxglove/rosmsg2-serialization) and prints, per file and topic, the schema, the messages decoded
// and the first failure, as JSON. Usage: node decode.mjs FILE.mcap [...]
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { decompress } from "fzstd";
import lz4 from "@foxglove/wasm-lz4";

async function decodeFile(path) {
  const handle = await open(path, "r");
  try {
    const readable = {
      size: async () => BigInt((await handle.stat()).size),
      read: async (offset, size) => {
        const buffer = new Uint8Array(Number(size));
        await handle.read(buffer, 0, Number(size), Number(offset));
        return buffer;
      },
    };
    const reader = await McapIndexedReader.Initialize({
      readable,
      decompressHandlers: {
        zstd: (data, size) => decompress(data, new Uint8Array(Number(size))),
        lz4: (data, size) => lz4(data, Number(size)),
      },
    });
    const readers = new Map();
    const topics = {};
    for (const [id, channel] of reader.channelsById) {
      const schema = reader.schemasById.get(channel.schemaId);
      topics[channel.topic] = { schema: schema?.name ?? null, encoding: channel.messageEncoding, decoded: 0, failed: 0, error: null, sample: null };
      try {
        if (schema?.encoding !== "ros2msg" || channel.messageEncoding !== "cdr") {
          throw new Error(`schema encoding ${schema?.encoding}, message encoding ${channel.messageEncoding}`);
        }
        readers.set(id, new MessageReader(parse(new TextDecoder().decode(schema.data), { ros2: true })));
      } catch (err) {
        topics[channel.topic].error = `schema: ${err.message}`;
      }
    }
    for await (const message of reader.readMessages()) {
      const channel = reader.channelsById.get(message.channelId);
      const entry = topics[channel.topic];
      const messageReader = readers.get(message.channelId);
      try {
        if (messageReader === undefined) throw new Error("no reader for its schema");
        const decoded = messageReader.readMessage(message.data);
        entry.decoded += 1;
        if (entry.sample === null) entry.sample = summary(decoded);
      } catch (err) {
        entry.failed += 1;
        entry.error ??= err.message;
      }
    }
    return topics;
  } finally {
    await handle.close();
  }
}

// a few fields a viewer relies on: the frame, and a point cloud's or image's size
function summary(msg) {
  const out = {};
  if (msg.header) out.frame_id = msg.header.frame_id;
  for (const key of ["width", "height", "point_step", "encoding"]) if (key in msg) out[key] = msg[key];
  if (Array.isArray(msg.fields)) out.fields = msg.fields.map((f) => f.name);
  return out;
}

await lz4.isLoaded; // its WebAssembly module
const result = {};
for (const path of process.argv.slice(2)) {
  try {
    result[path] = await decodeFile(path);
  } catch (err) {
    result[path] = { error: err.message };
  }
}
console.log(JSON.stringify(result));
