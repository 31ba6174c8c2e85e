// scripts/check-docs on small document trees of its own, with the real binaries: a sound tree
// passes with its counts, and each kind of breakage is caught and named (a checker that
// cannot fail checks nothing).
//
//   node tests/docs/check_docs_test.mjs --bin-dir build/bin
import { spawnSync } from "node:child_process";
import fs from "node:fs";
import os from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const checker = path.resolve(here, "../../scripts/check-docs");
const at = process.argv.indexOf("--bin-dir");
const bin = path.resolve(at > 0 ? process.argv[at + 1] : path.resolve(here, "../../build/bin"));

let failures = 0;
function expect(condition, what, output) {
  if (!condition) {
    ++failures;
    console.log(`FAILED: ${what}\n${output}`);
  } else {
    console.log(`ok: ${what}`);
  }
}

// A tree: README.md, docs/guide.md, docs/picture.png; `edit` changes the files' text.
function tree(edit = (files) => files) {
  const root = fs.mkdtempSync(path.join(os.tmpdir(), "check-docs-"));
  fs.mkdirSync(path.join(root, "docs"));
  const files = edit({
    "README.md": [
      "# Demo",
      "",
      "![The viewer](docs/picture.png) and [the guide](docs/guide.md#running-a-server).",
      "",
      "```sh",
      "build/bin/stereomap-server --store store --http 127.0.0.1:8080   # a comment --not-a-flag",
      "build/bin/stereomap-store --store store merge a b --into c",
      "```",
      "",
      "<!-- check-docs: run -->",
      "```sh",
      "test -f README.md",
      "```",
      "",
      "<!-- check-docs: run needs=no/such/data -->",
      "```sh",
      "false",
      "```",
      "",
    ].join("\n"),
    "docs/guide.md": [
      "# Guide",
      "",
      "## Running a server",
      "",
      "Start `stereomap-server --help`; back to the [front page](../README.md#demo).",
      "",
    ].join("\n"),
  });
  for (const [name, text] of Object.entries(files)) fs.writeFileSync(path.join(root, name), text);
  fs.writeFileSync(path.join(root, "docs", "picture.png"), "");
  return root;
}

function check(root) {
  const result = spawnSync(checker, ["--root", root, "--bin", bin], { encoding: "utf8" });
  const output = `${result.stdout}${result.stderr}`;
  fs.rmSync(root, { recursive: true, force: true });
  const last = output.trim().split("\n").pop();
  return { status: result.status, output, last };
}

const sound = check(tree());
expect(sound.status === 0, "a sound tree passes", sound.output);
expect(
  sound.last === "docs: 2 files, 3 links, 5 flags, 4 commands checked, 0 broken",
  `its last line counts what was checked ("${sound.last}")`,
  sound.output,
);
expect(/skipped \(no\/such\/data is absent\)/.test(sound.output), "a block whose data is absent is skipped and said", sound.output);

const breakages = [
  ["a link to a missing file", (f) => ({ ...f, "README.md": f["README.md"].replace("docs/guide.md#", "docs/gone.md#") }), /docs\/gone\.md#running-a-server: no such file/],
  ["an anchor that names no heading", (f) => ({ ...f, "README.md": f["README.md"].replace("#running-a-server", "#running-a-cluster") }), /no heading with anchor #running-a-cluster/],
  ["a missing image", (f) => ({ ...f, "README.md": f["README.md"].replace("picture.png", "nothing.png") }), /docs\/nothing\.png: no such file/],
  ["a link out of the repository", (f) => ({ ...f, "docs/guide.md": f["docs/guide.md"] + "[data](../../shared/data/README.md)\n" }), /outside the repository/],
  ["a flag the binary does not have", (f) => ({ ...f, "README.md": f["README.md"].replace("--http 127", "--listen 127") }), /stereomap-server: no flag --listen/],
  ["a subcommand's flag that is not there", (f) => ({ ...f, "README.md": f["README.md"].replace("--into c", "--onto c") }), /stereomap-store merge: no flag --onto/],
  ["a binary that is not built", (f) => ({ ...f, "docs/guide.md": f["docs/guide.md"].replace("stereomap-server --help", "stereomap-mapper --help") }), /stereomap-mapper: no such binary/],
  ["a marked block that fails", (f) => ({ ...f, "README.md": f["README.md"].replace("test -f README.md", "test -f NOTHING") }), /the block failed \(exit 1/],
  ["an issue number in a user doc", (f) => ({ ...f, "docs/guide.md": f["docs/guide.md"] + "Added for issue 42.\n" }), /cites an issue number/],
  ["a README over 15 kB", (f) => ({ ...f, "README.md": f["README.md"] + "x".repeat(15001) + "\n" }), /bytes: a front page is at most 15000/],
];
for (const [what, edit, named] of breakages) {
  const result = check(tree(edit));
  expect(result.status === 1 && named.test(result.output) && / 1 broken$/.test(result.last), `${what} is caught`, result.output);
}

console.log(`${failures === 0 ? "passed" : "FAILED"}: ${breakages.length + 3 - failures} of ${breakages.length + 3} checks`);
process.exit(failures === 0 ? 0 : 1);
