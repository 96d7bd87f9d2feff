// Bundle web/src/browser.js into the page's static script (npm run build).
// `node web/build.mjs [OUTFILE]`: another output file (the test compares the two).
// The output is deterministic: the same sources give the same bytes.
import { build } from "esbuild";
import { fileURLToPath } from "node:url";
import path from "node:path";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..");
const outfile = process.argv[2] ?? path.join(root, "src/telebot/apps/web/static/telebot-client.js");

try {
  await build({
    absWorkingDir: root,
    entryPoints: ["web/src/browser.js"],
    outfile,
    bundle: true,
    minify: true,
    format: "iife",
    target: "es2020", // BigInt
    platform: "browser",
    legalComments: "eof", // the @noble licence notices stay in the bundle
    charset: "utf8",
    logLevel: "warning",
  });
} catch {
  // esbuild has printed what was wrong.
  process.exit(1);
}
