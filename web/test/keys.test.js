import { test } from "node:test";
import assert from "node:assert/strict";
import { Keys, parseInvite, MAX_INVITE } from "../src/keys.js";
import { contactLine, encodeKey, generateKeyPair, parseContactLine } from "../src/identity.js";
import { memoryStore } from "../src/store.js";

const robotKey = () => encodeKey(generateKeyPair().publicKey);

test("a key is made once, named, and shown as keygen's contact line", async () => {
  const keys = new Keys(memoryStore());
  assert.equal(await keys.me(), null);
  await assert.rejects(keys.contactLine(), /no key yet/);
  const me = await keys.create("alice");
  assert.equal(me.privateKey.length, 32);
  const line = await keys.contactLine();
  assert.equal(line, contactLine("alice", me.publicKey));
  assert.deepEqual(parseContactLine(line).publicKey, me.publicKey);
  // Never replaced silently: robots know this key.
  await assert.rejects(keys.create("alice"), /has a key already/);
  await keys.rename("alice2");
  assert.equal((await keys.me()).name, "alice2");
  assert.deepEqual((await keys.me()).publicKey, me.publicKey);
  await assert.rejects(keys.rename("bad name"), (e) => !e.message.includes("\n"));
});

test("a bad name makes no key", async () => {
  const keys = new Keys(memoryStore());
  await assert.rejects(keys.create("no spaces please"));
  assert.equal(await keys.me(), null);
});

test("a damaged stored key is a one-line error, not a crash later", async () => {
  const store = memoryStore();
  await store.put("me", { name: "alice", privateKey: new Uint8Array(3), publicKey: new Uint8Array(32) });
  await assert.rejects(new Keys(store).me(), /damaged/);
});

test("robots are pinned from their line, listed by name, and a different key is KEY MISMATCH", async () => {
  const keys = new Keys(memoryStore());
  const k1 = robotKey(), k2 = robotKey();
  assert.deepEqual(await keys.pinLine(`telebot-x25519 ${k1} zeta`), { name: "zeta", key: k1, added: true });
  assert.equal((await keys.pin("alpha", k2, "invite")).added, true);
  assert.deepEqual((await keys.robots()).map((r) => [r.name, r.key, r.via]), [["alpha", k2, "invite"], ["zeta", k1, "pasted"]]);
  assert.match((await keys.robots())[0].fingerprint, /^SHA256:/);
  // The same key again: no change. Another key: refused, the pinned one stays.
  assert.equal((await keys.pin("zeta", k1)).added, false);
  await assert.rejects(keys.pin("zeta", k2), /^Error: KEY MISMATCH: robot zeta is pinned with key/);
  assert.deepEqual(await keys.robotKey("zeta"), parseContactLine(`telebot-x25519 ${k1} zeta`).publicKey);
  assert.equal(await keys.robotKey("nobody"), null);
  assert.equal(await keys.unpin("zeta"), true);
  assert.equal(await keys.unpin("zeta"), false);
  assert.equal((await keys.pin("zeta", k2)).added, true);
});

test("bad robot lines and keys are refused in one line", async () => {
  const keys = new Keys(memoryStore());
  for (const [name, key] of [["r", "short"], ["", robotKey()], ["two words", robotKey()], ["r", "x".repeat(100000)]]) {
    await assert.rejects(keys.pin(name, key), (e) => !e.message.includes("\n") && e.message.length < 200);
  }
  await assert.rejects(keys.pinLine("ssh-ed25519 AAAA robot"));
  assert.deepEqual(await keys.robots(), []);
});

test("an invite link's fragment is read, checked, and absent is null", () => {
  const key = robotKey();
  assert.equal(parseInvite(""), null);
  assert.equal(parseInvite("#robot=x"), null);
  assert.deepEqual(parseInvite(`#invite=abc_DEF-1&robot=guiabot&key=${key}`), { invite: "abc_DEF-1", robot: "guiabot", key });
  assert.deepEqual(parseInvite(`invite=t&robot=guiabot&key=${key}`).robot, "guiabot");
  const bad = [
    `#invite=&robot=guiabot&key=${key}`,
    `#invite=a%20b&robot=guiabot&key=${key}`,
    `#invite=${"a".repeat(MAX_INVITE + 1)}&robot=guiabot&key=${key}`,
    "#invite=t&robot=guiabot",
    `#invite=t&key=${key}`,
    "#invite=t&robot=guiabot&key=notakey",
    `#invite=t&robot=bad%20name&key=${key}`,
  ];
  for (const hash of bad) assert.throws(() => parseInvite(hash), (e) => !e.message.includes("\n"), hash);
});
