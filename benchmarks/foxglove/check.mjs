// A uwbd log as Foxglove reads it: Foxglove's own TypeScript MCAP library (@mcap/core, the
// indexed reader a viewer uses, with @mcap/support's decompressors and protobuf loader) and
// Foxglove's published schemas (@foxglove/schemas).
//
//   cd benchmarks/foxglove && npm install && node check.mjs LOG.mcap [LOG.mcap ...]
//
// For every channel: a schema; for JSON channels, a JSON Schema that Foxglove's JSON Schema
// reader accepts (the rules of parseJsonSchema in Foxglove's mcap-support, mirrored below:
// that package is not published) and that every message fits (Ajv); for foxglove.* channels,
// every message fits Foxglove's own schema of that name too, and every field uwbd's schema
// declares is one of Foxglove's; for protobuf channels (/raw/*), the FileDescriptorSet loads
// as Foxglove loads it and every message decodes; and every record's timestamp {sec, nsec}
// equals its log time exactly (t_ns, parsed as a JavaScript number, may not: it is above 2^53).
// Exit status 1 when anything fails.

import { open } from "node:fs/promises";

import foxgloveSchemas from "@foxglove/schemas/jsonschema.js";
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers, protobufFromBinaryDescriptor } from "@mcap/support";
import Ajv from "ajv";

const ajv = new Ajv({ strict: false, allErrors: false });
const official = foxgloveSchemas.default ?? foxgloveSchemas;
const decoder = new TextDecoder();
let failures = 0;

function fail(where, what) {
  failures += 1;
  console.log(`  FAIL ${where}: ${what}`);
}

// Foxglove's parseJsonSchema: what it throws on
function foxgloveAccepts(schema, where) {
  if (schema.type !== "object") throw new Error(`${where}: expected "type": "object"`);
  for (const [name, field] of Object.entries(schema.properties)) {
    const at = `${where}.${name}`;
    if (Array.isArray(field.oneOf)) {
      if (!field.oneOf.every((alt) => typeof alt.const === "number")) {
        throw new Error(`${at}: oneOf alternatives must have number values`);
      }
      continue;
    }
    switch (field.type) {
      case "boolean":
      case "number":
      case "integer":
        break;
      case "string":
        if (field.contentEncoding !== undefined && field.contentEncoding !== "base64") {
          throw new Error(`${at}: unsupported contentEncoding`);
        }
        break;
      case "object":
        foxgloveAccepts(field, at);
        break;
      case "array": {
        const items = field.items;
        if (items.type === "object") foxgloveAccepts(items, `${at}[]`);
        else if (!["boolean", "string", "number", "integer"].includes(items.type)) {
          throw new Error(`${at}: unsupported array item type ${JSON.stringify(items.type)}`);
        } else if (items.type === "string" && items.contentEncoding !== undefined) {
          throw new Error(`${at}: unsupported contentEncoding for array item`);
        }
        break;
      }
      default:
        throw new Error(`${at}: unsupported type ${JSON.stringify(field.type)}`);
    }
  }
}

// every property uwbd declares is one of Foxglove's, of the same type (at the top level,
// uwbd's own fields beside Foxglove's, which Foxglove ignores, are listed in `extra`)
function subsetOf(ours, theirs, where, extra = undefined) {
  for (const [name, field] of Object.entries(ours.properties ?? {})) {
    const other = theirs.properties?.[name];
    const at = `${where}.${name}`;
    if (other === undefined) {
      if (extra !== undefined) extra.push(name);
      else fail(at, "not a field of Foxglove's schema");
      continue;
    }
    if ((field.type ?? "enum") !== (other.type ?? "enum")) {
      fail(at, `type ${field.type} where Foxglove's is ${other.type}`);
    } else if (field.type === "object") {
      subsetOf(field, other, at);
    } else if (field.type === "array" && field.items.type === "object") {
      subsetOf(field.items, other.items, `${at}[]`);
    }
  }
}

async function check(path) {
  console.log(path);
  const handle = await open(path, "r");
  try {
    const reader = await McapIndexedReader.Initialize({
      readable: new FileHandleReadable(handle),
      decompressHandlers: await loadDecompressHandlers(),
    });
    const checkers = new Map();
    for (const channel of reader.channelsById.values()) {
      const schema = reader.schemasById.get(channel.schemaId);
      const where = `${channel.topic} (${channel.messageEncoding}, ${schema?.name ?? "no schema"})`;
      if (schema === undefined) {
        fail(where, "no schema");
        continue;
      }
      const entry = { where, count: 0, bad: 0, exactTimes: 0, roundedTNs: 0 };
      if (channel.messageEncoding === "json") {
        const ours = JSON.parse(decoder.decode(schema.data));
        try {
          foxgloveAccepts(ours, channel.topic);
        } catch (err) {
          fail(where, `Foxglove's JSON Schema reader would refuse it: ${err.message}`);
        }
        entry.validators = [["uwbd's schema", ajv.compile(ours)]];
        const name = schema.name.startsWith("foxglove.") ? schema.name.slice(9) : undefined;
        if (name !== undefined) {
          if (official[name] === undefined) fail(where, `Foxglove has no schema ${name}`);
          else {
            entry.extra = [];
            subsetOf(ours, official[name], channel.topic, entry.extra);
            entry.validators.push([`Foxglove's ${name}`, ajv.compile(official[name])]);
          }
        }
        entry.decode = (data) => JSON.parse(decoder.decode(data));
      } else if (channel.messageEncoding === "protobuf") {
        const type = protobufFromBinaryDescriptor(schema.data).lookupType(schema.name);
        entry.validators = [];
        entry.decode = (data) => type.toObject(type.decode(data));
      } else {
        fail(where, `message encoding ${channel.messageEncoding} Foxglove cannot open`);
        continue;
      }
      checkers.set(channel.id, entry);
    }
    for await (const message of reader.readMessages()) {
      const entry = checkers.get(message.channelId);
      if (entry === undefined) continue;
      entry.count += 1;
      let record;
      try {
        record = entry.decode(message.data);
      } catch (err) {
        entry.bad += 1;
        if (entry.bad === 1) fail(entry.where, `does not decode: ${err.message}`);
        continue;
      }
      for (const [label, validate] of entry.validators) {
        if (!validate(record)) {
          entry.bad += 1;
          if (entry.bad === 1) {
            fail(entry.where, `${label}: ${ajv.errorsText(validate.errors)}`);
          }
        }
      }
      const t = record.timestamp;
      if (t !== undefined) {
        if (BigInt(t.sec) * 1_000_000_000n + BigInt(t.nsec) === message.logTime) {
          entry.exactTimes += 1;
        } else if (entry.bad++ === 0) fail(entry.where, "timestamp is not the log time");
      }
      if (typeof record.t_ns === "number" && BigInt(record.t_ns) !== message.logTime) {
        entry.roundedTNs += 1;
      }
    }
    for (const e of checkers.values()) {
      const times = e.exactTimes ? `, timestamp exact in ${e.exactTimes}` : "";
      const rounded = e.roundedTNs ? `, t_ns rounded by JSON.parse in ${e.roundedTNs}` : "";
      const extra = e.extra?.length ? `; uwbd's own fields beside Foxglove's: ${e.extra}` : "";
      console.log(
        `  ${e.where}: ${e.count} messages, ${e.count - e.bad} valid${times}${rounded}${extra}`);
    }
  } finally {
    await handle.close();
  }
}

const logs = process.argv.slice(2);
if (logs.length === 0) {
  console.log("usage: node check.mjs LOG.mcap [LOG.mcap ...]");
  process.exit(2);
}
for (const log of logs) await check(log);
console.log(failures === 0 ? "all channels open and every message fits" : `${failures} failures`);
process.exit(failures === 0 ? 0 : 1);
