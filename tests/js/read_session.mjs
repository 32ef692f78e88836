// Reads an MCAP file with the official TypeScript reader (@mcap/core) and prints one JSON object that
// describes what it read, for tests/unit/capture/test_ts_reader.py to compare with the Python reader.
//
//   node read_session.mjs SESSION.mcap
//
// The indexed reader (McapIndexedReader) reads the file through its summary: header, schemas, channels,
// every message of every channel, every metadata record and attachment. A file it cannot open (no
// summary or footer, e.g. a killed recorder's file) or whose summary indexes no chunks is read by the
// stream reader (McapStreamReader) from the start up to where it stops, and "indexError" says why; what
// stopped the stream reader is reported in "error", not thrown. The stream
// reader also reads an intact file once more, in file order, for "fileOrder": the order messages were
// written, in which log times must be monotonic per channel.
//
// Message payloads are not decoded (protobuf, json and perfcap's own encodings alike): that is checked
// elsewhere. Times are bigints, printed as decimal strings. The exit status is 0 whenever a report is
// printed, however damaged the file; 2 for a usage error or a file that cannot be opened at all.

import { open } from "node:fs/promises";

import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { loadDecompressHandlers } from "@mcap/support";

const STREAM_READ_BYTES = 1 << 20;

function errorText(err) {
  return err instanceof Error ? `${err.name}: ${err.message}` : String(err);
}

function schemaInfo(schema) {
  return { id: schema.id, name: schema.name, encoding: schema.encoding, dataLength: schema.data.byteLength };
}

function channelInfo(channel) {
  return {
    id: channel.id,
    topic: channel.topic,
    messageEncoding: channel.messageEncoding,
    schemaId: channel.schemaId,
    metadataKeys: [...channel.metadata.keys()].sort(),
  };
}

// Per-channel message statistics, in the order the messages are given.
class MessageTally {
  constructor() {
    this.byChannel = new Map();
  }

  add(message) {
    let t = this.byChannel.get(message.channelId);
    if (t === undefined) {
      t = {
        count: 0,
        dataBytes: 0,
        firstLogTime: message.logTime,
        lastLogTime: message.logTime,
        minLogTime: message.logTime,
        maxLogTime: message.logTime,
        firstPublishTime: message.publishTime,
        lastPublishTime: message.publishTime,
        logTimeMonotonic: true,
        publishAfterLog: false,
      };
      this.byChannel.set(message.channelId, t);
    }
    if (message.logTime < t.lastLogTime) {
      t.logTimeMonotonic = false;
    }
    if (message.publishTime > message.logTime) {
      t.publishAfterLog = true;
    }
    if (message.logTime < t.minLogTime) {
      t.minLogTime = message.logTime;
    }
    if (message.logTime > t.maxLogTime) {
      t.maxLogTime = message.logTime;
    }
    t.count += 1;
    t.dataBytes += message.data.byteLength;
    t.lastLogTime = message.logTime;
    t.lastPublishTime = message.publishTime;
  }

  get total() {
    let n = 0;
    for (const t of this.byChannel.values()) {
      n += t.count;
    }
    return n;
  }

  toJSON() {
    const out = {};
    for (const [id, t] of [...this.byChannel.entries()].sort((a, b) => a[0] - b[0])) {
      out[String(id)] = {
        count: t.count,
        dataBytes: t.dataBytes,
        firstLogTime: String(t.firstLogTime),
        lastLogTime: String(t.lastLogTime),
        minLogTime: String(t.minLogTime),
        maxLogTime: String(t.maxLogTime),
        firstPublishTime: String(t.firstPublishTime),
        lastPublishTime: String(t.lastPublishTime),
        logTimeMonotonic: t.logTimeMonotonic,
        publishAfterLog: t.publishAfterLog,
      };
    }
    return out;
  }
}

function fileReadable(handle, size) {
  return {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      if (offset + length > BigInt(size)) {
        throw new Error(`read of ${length} bytes at ${offset} is past the end of the file (${size} bytes)`);
      }
      const buf = new Uint8Array(Number(length));
      let got = 0;
      while (got < buf.byteLength) {
        const { bytesRead } = await handle.read(buf, got, buf.byteLength - got, Number(offset) + got);
        if (bytesRead === 0) {
          throw new Error(`file ended at ${Number(offset) + got} while reading ${length} bytes at ${offset}`);
        }
        got += bytesRead;
      }
      return buf;
    },
  };
}

async function readIndexed(handle, size, decompressHandlers) {
  const reader = await McapIndexedReader.Initialize({ readable: fileReadable(handle, size), decompressHandlers });
  const tally = new MessageTally();
  const result = {
    reader: "indexed",
    error: null,
    complete: false,
    profile: reader.header.profile,
    library: reader.header.library,
    schemas: [...reader.schemasById.values()].sort((a, b) => a.id - b.id).map(schemaInfo),
    channels: [...reader.channelsById.values()].sort((a, b) => a.id - b.id).map(channelInfo),
    metadata: [],
    attachments: [],
    statistics: null,
    chunkCount: reader.chunkIndexes.length,
    chunkCompressions: [...new Set(reader.chunkIndexes.map((c) => c.compression))].sort(),
  };
  if (reader.statistics !== undefined) {
    const s = reader.statistics;
    const counts = {};
    for (const [id, n] of [...s.channelMessageCounts.entries()].sort((a, b) => a[0] - b[0])) {
      counts[String(id)] = String(n);
    }
    result.statistics = {
      messageCount: String(s.messageCount),
      schemaCount: s.schemaCount,
      channelCount: s.channelCount,
      attachmentCount: s.attachmentCount,
      metadataCount: s.metadataCount,
      chunkCount: s.chunkCount,
      messageStartTime: String(s.messageStartTime),
      messageEndTime: String(s.messageEndTime),
      channelMessageCounts: counts,
    };
  }
  try {
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      tally.add(message);
    }
    for await (const metadata of reader.readMetadata()) {
      result.metadata.push(metadata.name);
    }
    for await (const attachment of reader.readAttachments({ validateCrcs: true })) {
      result.attachments.push(attachment.name);
    }
    result.complete = true;
  } catch (err) {
    result.error = errorText(err);
  }
  result.messages = tally.toJSON();
  result.messageCount = tally.total;
  return result;
}

async function readStream(handle, size, decompressHandlers) {
  const reader = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  const tally = new MessageTally();
  const schemas = new Map();
  const channels = new Map();
  const result = {
    reader: "stream",
    error: null,
    complete: false,
    profile: null,
    library: null,
    metadata: [],
    attachments: [],
    statistics: null,
    bytesRead: 0,
  };
  const buf = new Uint8Array(STREAM_READ_BYTES);
  let position = 0;
  try {
    for (;;) {
      const { bytesRead } = await handle.read(buf, 0, buf.byteLength, position);
      if (bytesRead === 0) {
        break;
      }
      position += bytesRead;
      reader.append(buf.slice(0, bytesRead));
      for (let record; (record = reader.nextRecord()); ) {
        switch (record.type) {
          case "Header":
            result.profile = record.profile;
            result.library = record.library;
            break;
          case "Schema":
            schemas.set(record.id, record);
            break;
          case "Channel":
            channels.set(record.id, record);
            break;
          case "Message":
            tally.add(record);
            break;
          case "Metadata":
            result.metadata.push(record.name);
            break;
          case "Attachment":
            result.attachments.push(record.name);
            break;
          default:
            break;
        }
      }
      if (reader.done()) {
        break;
      }
    }
    result.complete = reader.done();
    if (!result.complete) {
      result.error = `file ends before the MCAP footer: ${reader.bytesRemaining()} bytes of an incomplete record left`;
    }
  } catch (err) {
    result.error = errorText(err);
  }
  result.bytesRead = position;
  result.schemas = [...schemas.values()].sort((a, b) => a.id - b.id).map(schemaInfo);
  result.channels = [...channels.values()].sort((a, b) => a.id - b.id).map(channelInfo);
  result.messages = tally.toJSON();
  result.messageCount = tally.total;
  return result;
}

function fileOrderSummary(streamResult) {
  const perChannel = {};
  for (const [id, t] of Object.entries(streamResult.messages)) {
    perChannel[id] = { count: t.count, dataBytes: t.dataBytes, logTimeMonotonic: t.logTimeMonotonic };
  }
  return {
    error: streamResult.error,
    complete: streamResult.complete,
    messageCount: streamResult.messageCount,
    messages: perChannel,
  };
}

async function main(argv) {
  if (argv.length !== 1) {
    process.stderr.write("usage: node read_session.mjs SESSION.mcap\n");
    return 2;
  }
  const path = argv[0];
  let handle;
  try {
    handle = await open(path, "r");
  } catch (err) {
    process.stderr.write(`cannot open ${path}: ${errorText(err)}\n`);
    return 2;
  }
  try {
    const { size } = await handle.stat();
    const decompressHandlers = await loadDecompressHandlers();
    let result;
    let indexError = null;
    try {
      result = await readIndexed(handle, size, decompressHandlers);
      if (result.chunkCount === 0) {
        // the indexed reader reads messages only out of indexed chunks: none here, whatever the statistics say
        indexError = "the summary indexes no chunks: messages outside chunks are read by the stream reader";
        result = undefined;
      }
    } catch (err) {
      indexError = errorText(err);
    }
    const stream = await readStream(handle, size, decompressHandlers);
    if (result === undefined) {
      result = stream;
    }
    result.indexError = indexError;
    result.fileOrder = fileOrderSummary(stream);
    result.logTimesMonotonic = Object.values(result.fileOrder.messages).every((t) => t.logTimeMonotonic);
    result.publishAfterLog = Object.values(result.messages).some((t) => t.publishAfterLog);
    const report = { file: path, size, ...result };
    process.stdout.write(`${JSON.stringify(report)}\n`);
    return 0;
  } finally {
    await handle.close();
  }
}

process.exitCode = await main(process.argv.slice(2));
