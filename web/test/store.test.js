import { test } from "node:test";
import assert from "node:assert/strict";
import { memoryStore, indexedDbStore } from "../src/store.js";

test("the memory store keeps bytes as bytes and copies what it is given", async () => {
  const store = memoryStore();
  const bytes = new Uint8Array([1, 2, 3]);
  await store.put("me", { name: "alice", privateKey: bytes });
  bytes[0] = 9; // the caller's array changing afterwards changes nothing stored
  const got = await store.get("me");
  assert.ok(got.privateKey instanceof Uint8Array);
  assert.deepEqual([...got.privateKey], [1, 2, 3]);
  got.name = "mallory"; // nor does changing what get returned
  assert.equal((await store.get("me")).name, "alice");
  await store.delete("me");
  assert.equal(await store.get("me"), undefined);
  assert.equal(store.persistent, false);
});

test("without IndexedDB the browser store says so in one line", async () => {
  await assert.rejects(indexedDbStore(undefined), /no IndexedDB/);
});
