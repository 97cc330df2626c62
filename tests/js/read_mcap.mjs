// Foxglove's MCAP reader (@mcap/core, what the Foxglove app reads logs with) on one log: the
// summary and its indexes, then every message through them with every chunk's CRC checked.
// Prints {"topics": {topic: count}, "chunks": N, "attachments": N, "metadata": N} as JSON and
// exits 0, or prints the reader's error and exits 1.
//
//   node tests/js/read_mcap.mjs LOG.mcap
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import zstd from "@foxglove/wasm-zstd";

const path = process.argv[2];
if (!path) {
  console.error("usage: node read_mcap.mjs LOG.mcap");
  process.exit(2);
}
try {
  await zstd.isLoaded;
  const file = await open(path, "r");
  const size = (await file.stat()).size;
  const readable = {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const bytes = new Uint8Array(Number(length));
      const { bytesRead } = await file.read(bytes, 0, Number(length), Number(offset));
      if (bytesRead !== Number(length)) throw new Error(`short read at ${offset}`);
      return bytes;
    },
  };
  const reader = await McapIndexedReader.Initialize({
    readable,
    decompressHandlers: { zstd: (data, decompressedSize) => zstd.decompress(data, Number(decompressedSize)) },
  });
  const topics = {};
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    const topic = reader.channelsById.get(message.channelId).topic;
    topics[topic] = (topics[topic] ?? 0) + 1;
  }
  console.log(JSON.stringify({
    topics,
    chunks: reader.chunkIndexes.length,
    attachments: reader.attachmentIndexes.length,
    metadata: reader.metadataIndexes.length,
  }));
  await file.close();
} catch (error) {
  console.error(`@mcap/core cannot read ${path}: ${error?.stack ?? error}`);
  process.exit(1);
}
