// Reads an MCAP log with Foxglove's own MCAP library (@mcap/core, indexed reader) and checks what
// Foxglove needs of it:
//  - every schema is JSON Schema that Foxglove's loader takes: "$schema" declared, one scalar
//    "type" per field (no ["string","null"] unions, no anyOf/oneOf but an enum's consts), no
//    arrays of arrays, no tuple items (prefixItems, items given as a list);
//  - every message is JSON (no NaN/Infinity tokens) and validates against its channel's schema
//    (ajv, draft 2020-12);
//  - the foxglove.* schemas (well-known, with a panel of their own) are the published ones
//    (@foxglove/schemas: the same fields, types, bounds and required lists; descriptions aside),
//    and their messages validate against those;
//  - the frame tree (foxglove.FrameTransform / FrameTransforms, what the 3D panel draws with):
//    every transform's frames, each frame with one parent, all hanging from one root; and the
//    URDF on /robot_description (what the 3D panel's URDF layer reads): every link of it is a
//    frame of the tree, so each link's visuals have a pose. Reported under "tf".
// Prints one JSON report; exit status 1 when anything is wrong, 2 on a usage error.
//
//   node check_mcap.mjs FILE.mcap
import { open } from "node:fs/promises";

import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";
import * as foxgloveSchemas from "@foxglove/schemas/jsonschema.js";
import Ajv2020 from "ajv/dist/2020.js";

const path = process.argv[2];
if (!path) {
  console.error("usage: node check_mcap.mjs FILE.mcap");
  process.exit(2);
}

function foxgloveProblems(schema) {
  const problems = [];
  if (typeof schema.$schema !== "string") problems.push("no $schema");
  const walk = (node, where) => {
    if (Array.isArray(node)) {
      node.forEach((n, i) => walk(n, `${where}[${i}]`));
      return;
    }
    if (node === null || typeof node !== "object") return;
    if (Array.isArray(node.type)) problems.push(`${where}: a union type ${JSON.stringify(node.type)}`);
    for (const k of ["anyOf", "oneOf"]) {      // an enum as oneOf of consts (Foxglove's own form) is fine
      if (k in node && !(Array.isArray(node[k]) && node[k].every((alt) => alt && "const" in alt))) {
        problems.push(`${where}: ${k} (a union)`);
      }
    }
    if (node.type === "array") {
      if ("prefixItems" in node || Array.isArray(node.items)) problems.push(`${where}: tuple items`);
      else if (node.items && node.items.type === "array") problems.push(`${where}: an array of arrays`);
    }
    for (const [k, v] of Object.entries(node)) {
      if (k === "enum" || k === "required" || k === "examples" || k === "default") continue;
      walk(v, where ? `${where}.${k}` : k);
    }
  };
  walk(schema, "");
  return problems;
}

// A schema with what Foxglove reads of it only: no descriptions, comments or dialect.
function shape(node) {
  if (Array.isArray(node)) return node.map(shape);
  if (node === null || typeof node !== "object") return node;
  const out = {};
  for (const k of Object.keys(node).sort()) {
    if (k === "description" || k === "$comment" || k === "$schema" || k === "$id") continue;
    out[k] = shape(node[k]);
  }
  return out;
}

const fh = await open(path, "r");
const reader = await McapIndexedReader.Initialize({
  readable: new FileHandleReadable(fh),
  decompressHandlers: await loadDecompressHandlers(),
});
const ajv = new Ajv2020({ strict: false, allErrors: true, validateFormats: false });
const report = { file: path, schemas: {}, messages: 0, invalid: 0, problems: [] };
const validators = new Map();       // schema id -> validate function
const problem = (text) => {
  if (report.problems.length < 50) report.problems.push(text);
};

for (const [id, schema] of reader.schemasById) {
  const entry = { encoding: schema.encoding, messages: 0, invalid: 0 };
  report.schemas[schema.name] = entry;
  if (schema.encoding !== "jsonschema") {
    problem(`${schema.name}: schema encoding ${schema.encoding}, not jsonschema`);
    continue;
  }
  let parsed;
  try {
    parsed = JSON.parse(new TextDecoder().decode(schema.data));
  } catch (err) {
    problem(`${schema.name}: schema is not JSON (${err.message})`);
    continue;
  }
  for (const p of foxgloveProblems(parsed)) problem(`${schema.name}: ${p}`);
  if (schema.name.startsWith("foxglove.")) {
    const published = foxgloveSchemas[schema.name.slice("foxglove.".length)];
    if (!published) problem(`${schema.name}: no such schema in @foxglove/schemas`);
    else {
      validators.set(`published:${id}`, ajv.compile({ ...published, $id: `published/${schema.name}` }));
      if (JSON.stringify(shape(parsed)) !== JSON.stringify(shape(published))) {
        problem(`${schema.name}: differs from the published schema (@foxglove/schemas)`);
      }
    }
  }
  try {
    validators.set(id, ajv.compile({ ...parsed, $id: `bsc/${id}` }));
  } catch (err) {
    problem(`${schema.name}: ajv cannot compile it (${err.message})`);
  }
}

const tf = { messages: 0, transforms: 0, parents: {}, urdf: null, urdf_links: [], urdf_messages: 0 };
const takeTransform = (t, where) => {
  tf.transforms += 1;
  const seen = tf.parents[t.child_frame_id];
  if (seen !== undefined && seen !== t.parent_frame_id) {
    problem(`${where}: frame ${t.child_frame_id} has two parents (${seen}, ${t.parent_frame_id})`);
  }
  tf.parents[t.child_frame_id] = t.parent_frame_id;
};

const channels = reader.channelsById;
for await (const msg of reader.readMessages()) {
  report.messages += 1;
  const channel = channels.get(msg.channelId);
  const schema = reader.schemasById.get(channel.schemaId);
  const entry = report.schemas[schema?.name ?? "(no schema)"] ?? (report.schemas["(no schema)"] = { messages: 0, invalid: 0 });
  entry.messages += 1;
  let value;
  try {
    value = JSON.parse(new TextDecoder().decode(msg.data));
  } catch (err) {
    entry.invalid += 1;
    report.invalid += 1;
    problem(`${channel.topic} at ${msg.logTime}: not JSON (${err.message})`);
    continue;
  }
  const where = `${channel.topic} at ${msg.logTime}`;
  if (schema?.name === "foxglove.FrameTransforms" && Array.isArray(value?.transforms)) {
    tf.messages += 1;
    value.transforms.forEach((t) => takeTransform(t, where));
  } else if (schema?.name === "foxglove.FrameTransform" && value && typeof value === "object") {
    tf.messages += 1;
    takeTransform(value, where);
  } else if (channel.topic === "/robot_description") {
    tf.urdf_messages += 1;
    if (typeof value?.data !== "string") problem(`${where}: no URDF text in its data field`);
    else if (tf.urdf === null) tf.urdf = value.data;
    else if (tf.urdf !== value.data) problem(`${where}: another URDF than the first`);
  }
  for (const key of [channel.schemaId, `published:${channel.schemaId}`]) {
    const validate = validators.get(key);
    if (validate && !validate(value)) {
      entry.invalid += 1;
      report.invalid += 1;
      problem(`${channel.topic} at ${msg.logTime}: ${key === channel.schemaId ? "" : "published schema: "}` +
              ajv.errorsText(validate.errors));
    }
  }
}
await fh.close();

if (tf.messages > 0 || tf.urdf_messages > 0) {
  const frames = new Set([...Object.keys(tf.parents), ...Object.values(tf.parents)]);
  const roots = [...frames].filter((f) => tf.parents[f] === undefined);
  if (tf.messages > 0 && roots.length !== 1) problem(`tf: ${roots.length} roots (${roots.join(", ")}), not one tree`);
  for (const f of Object.keys(tf.parents)) {          // a cycle never reaches a root
    let g = f;
    for (let n = 0; n <= frames.size && tf.parents[g] !== undefined; n += 1) g = tf.parents[g];
    if (tf.parents[g] !== undefined) problem(`tf: frame ${f} is in a cycle`);
  }
  if (tf.urdf !== null) {
    tf.urdf_links = [...tf.urdf.matchAll(/<link\s+name="([^"]+)"/g)].map((m) => m[1]).sort();
    for (const link of tf.urdf_links) if (!frames.has(link)) problem(`tf: URDF link ${link} is no frame of /tf`);
  }
  report.tf = { messages: tf.messages, transforms: tf.transforms, roots, frames: [...frames].sort(),
                urdf_messages: tf.urdf_messages, urdf_links: tf.urdf_links };
}
report.ok = report.problems.length === 0 && report.messages > 0;
console.log(JSON.stringify(report, (k, v) => (typeof v === "bigint" ? Number(v) : v), 1));
process.exit(report.ok ? 0 : 1);
