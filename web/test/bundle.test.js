// The committed browser bundle is what web/build.mjs makes of the sources now: a stale
// bundle (sources changed, `npm run build` forgotten) fails here.
import { test } from "node:test";
import assert from "node:assert/strict";
import { execFileSync } from "node:child_process";
import { mkdtempSync, readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "../..");
const committed = path.join(root, "src/telebot/apps/web/static/telebot-client.js");

test("the committed bundle equals a fresh build", () => {
  const dir = mkdtempSync(path.join(tmpdir(), "telebot-bundle-"));
  try {
    const fresh = path.join(dir, "telebot-client.js");
    execFileSync(process.execPath, [path.join(root, "web/build.mjs"), fresh], { stdio: "pipe" });
    const built = readFileSync(fresh, "utf8");
    assert.ok(built.includes("globalThis.telebot"));
    assert.ok(
      readFileSync(committed, "utf8") === built,
      "src/telebot/apps/web/static/telebot-client.js is stale: run `npm run build` and commit it",
    );
  } finally {
    rmSync(dir, { recursive: true, force: true });
  }
});

test("the bundle gives the API on window.telebot", async () => {
  const text = readFileSync(committed, "utf8");
  const scope = /** @type {any} */ ({});
  new Function("globalThis", text)(scope);
  const names = [
    "Endpoint", "encodeKey", "decodeKey", "contactLine", "fingerprint", "KeyMismatch", "ProtocolError",
    "RobotSession", "packMedia", "realClock", "backoffDelay", "RequestFailed", "STOP_HOWS", "sayText",
    "decodeMapPng", "pngSize", "CODEC_IDS", "CODEC_NAMES",
  ];
  for (const name of names) assert.ok(scope.telebot[name], name);
  assert.equal(scope.telebot.encodeKey(new Uint8Array(32)), "A".repeat(43));
  assert.equal(scope.telebot.CODEC_NAMES[scope.telebot.CODEC_IDS.jpeg], "jpeg");
  assert.equal(scope.telebot.sayText("say hello"), "hello");
  // A RobotSession runs from the bundle: on a call that fails, start() rejects with its error.
  /** @type {object[]} */
  const emitted = [];
  const session = new scope.telebot.RobotSession({
    connect: async () => {
      throw new scope.telebot.KeyMismatch("KEY MISMATCH: test");
    },
    emit: (msg) => emitted.push(msg),
  });
  await assert.rejects(session.start(), /KEY MISMATCH: test/);
});
