/**
 * Where the browser keeps the user's key and pinned robots: a small key-value store in
 * IndexedDB (database `telebot`, object store `kv`), or in memory (node tests, and a
 * browser without IndexedDB, where nothing survives a reload and the page says so).
 *
 * Values are stored by structured clone: a Uint8Array stays a Uint8Array.
 * @module store
 */

/**
 * @typedef {object} Store
 * @property {(key: string) => Promise<any>} get  the value, or undefined
 * @property {(key: string, value: any) => Promise<void>} put
 * @property {(key: string) => Promise<void>} delete
 * @property {boolean} persistent  whether what is put survives a reload
 */

/**
 * A store in memory.
 * @returns {Store}
 */
export function memoryStore() {
  const map = new Map();
  return {
    persistent: false,
    async get(key) { return structuredClone(map.get(key)); },
    async put(key, value) { map.set(key, structuredClone(value)); },
    async delete(key) { map.delete(key); },
  };
}

/**
 * The browser's store: IndexedDB, opened once.
 * @param {IDBFactory} [idb] (indexedDB by default)
 * @param {string} [dbName]
 * @returns {Promise<Store>}
 */
export async function indexedDbStore(idb = globalThis.indexedDB, dbName = "telebot") {
  if (!idb) throw new Error("this browser has no IndexedDB: a key made here would be lost");
  const db = await new Promise((resolve, reject) => {
    const req = idb.open(dbName, 1);
    req.onupgradeneeded = () => req.result.createObjectStore("kv");
    req.onsuccess = () => resolve(req.result);
    req.onerror = () => reject(new Error("cannot open the browser's key store: " + (req.error && req.error.message)));
    req.onblocked = () => reject(new Error("the browser's key store is busy in another tab: close it and reload"));
  });
  const run = (mode, fn) => new Promise((resolve, reject) => {
    const tx = db.transaction("kv", mode);
    const req = fn(tx.objectStore("kv"));
    tx.oncomplete = () => resolve(req.result);
    tx.onerror = () => reject(new Error("the browser's key store failed: " + (tx.error && tx.error.message)));
    tx.onabort = tx.onerror;
  });
  return {
    persistent: true,
    get: (key) => run("readonly", (s) => s.get(key)),
    put: async (key, value) => { await run("readwrite", (s) => s.put(value, key)); },
    delete: async (key) => { await run("readwrite", (s) => s.delete(key)); },
  };
}
