// Decode CDR messages with Foxglove's TypeScript decoder from their ros2msg definitions.
// stdin: JSON list of {schema, data (base64)}; stdout: JSON list of the decoded messages, with
// 64-bit integers beyond 2**53 as strings and byte arrays as base64 (what the test compares).
import { readFileSync } from "node:fs";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

function plain(v) {
  if (typeof v === "bigint") {
    return v > BigInt(Number.MAX_SAFE_INTEGER) || v < -BigInt(Number.MAX_SAFE_INTEGER)
      ? v.toString() : Number(v);
  }
  if (v instanceof Uint8Array) return { bytes: Buffer.from(v).toString("base64") };
  if (ArrayBuffer.isView(v)) return Array.from(v, plain);
  if (Array.isArray(v)) return v.map(plain);
  if (v !== null && typeof v === "object") {
    return Object.fromEntries(Object.entries(v).map(([k, x]) => [k, plain(x)]));
  }
  return v;
}

const cases = JSON.parse(readFileSync(0, "utf8"));
const out = cases.map(({ schema, data }) => {
  const reader = new MessageReader(parse(schema, { ros2: true }));
  return plain(reader.readMessage(Buffer.from(data, "base64")));
});
process.stdout.write(JSON.stringify(out));
