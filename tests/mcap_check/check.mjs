// Reads an MCAP file with the TypeScript implementation (@mcap/core), both as
// Foxglove does (indexed, by topic, in log-time order) and as a stream, with
// CRC checks on, and prints what it found as one JSON object.
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { decompress } from "fzstd";
import { createHash } from "node:crypto";
import { open, readFile } from "node:fs/promises";

const path = process.argv[2];
const decompressHandlers = {
  zstd: (buffer, decompressedSize) => decompress(buffer, new Uint8Array(Number(decompressedSize))),
};

const handle = await open(path, "r");
const readable = {
  size: async () => BigInt((await handle.stat()).size),
  read: async (offset, size) => {
    const out = new Uint8Array(Number(size));
    await handle.read(out, 0, Number(size), Number(offset));
    return out;
  },
};
const indexed = await McapIndexedReader.Initialize({ readable, decompressHandlers });
const topics = {};
const perTopic = {};
const digests = {};  // per topic: sha256 over each message's log time (decimal, then a newline) and data, in order
for (const channel of indexed.channelsById.values()) {
  const schema = indexed.schemasById.get(channel.schemaId);
  topics[channel.topic] = { schema: schema?.name, schemaEncoding: schema?.encoding,
                            messageEncoding: channel.messageEncoding };
}
let indexedCount = 0;
let backwards = 0;
const last = {};
for (const channel of indexed.channelsById.values()) {
  // one topic at a time, as a Foxglove panel asks: this uses the message indexes
  let n = 0;
  const hash = createHash("sha256");
  for await (const message of indexed.readMessages({ topics: [channel.topic], validateCrcs: true })) {
    hash.update(`${message.logTime}\n`);
    hash.update(message.data);
    JSON.parse(new TextDecoder().decode(message.data));
    if (last[channel.topic] !== undefined && message.logTime < last[channel.topic]) backwards++;
    last[channel.topic] = message.logTime;
    n++;
  }
  perTopic[channel.topic] = n;
  digests[channel.topic] = hash.digest("hex");
  indexedCount += n;
}
await handle.close();

const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
stream.append(await readFile(path));
let streamCount = 0;
let metadata = null;
for (let record; (record = stream.nextRecord()); ) {
  if (record.type === "Message") streamCount++;
  if (record.type === "Metadata" && record.name === "whiztap") metadata = Object.fromEntries(record.metadata);
}
console.log(JSON.stringify({ topics, perTopic, digests, indexedCount, streamCount, backwards, metadata,
                             done: stream.done(), statistics: Number(indexed.statistics?.messageCount ?? -1) }));
