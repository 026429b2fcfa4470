// Validate a .glb with the Khronos glTF validator (npm: gltf-validator, installed under tests/node).
// Usage: node tests/gltf_validate.js FILE.glb
// Prints one JSON object: {numErrors, numWarnings, numInfos, messages: [{code, severity, pointer, message}]}.
"use strict";
const fs = require("fs");
const path = require("path");

const validator = require(path.join(__dirname, "node", "node_modules", "gltf-validator"));
const file = process.argv[2];
const bytes = new Uint8Array(fs.readFileSync(file));
validator
  .validateBytes(bytes, { maxIssues: 0, writeTimestamp: false })
  .then((report) => {
    const issues = report.issues;
    const messages = issues.messages.map((m) => ({
      code: m.code,
      severity: m.severity,
      pointer: m.pointer,
      message: m.message,
    }));
    const summary = {
      numErrors: issues.numErrors,
      numWarnings: issues.numWarnings,
      numInfos: issues.numInfos,
      messages: messages.slice(0, 50),
    };
    process.stdout.write(JSON.stringify(summary) + "\n");
  })
  .catch((error) => {
    process.stderr.write(String(error) + "\n");
    process.exit(2);
  });
