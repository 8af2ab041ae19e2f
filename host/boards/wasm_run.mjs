// Run MicroPython code (read from stdin) under the 32-bit WebAssembly port, with the
// project's firmware/ package copied into the interpreter's filesystem at /firmware.
// Exit status 0 on success, 3 when the Python code raised (traceback on stderr).
// Used by host/boards/mpyrun.py; stdout/stderr callbacks are passed so no error vanishes.
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";
import fs from "fs";
import path from "path";
import { fileURLToPath } from "url";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..", "..");
const heapsize = parseInt(process.env.UPRIGHT_WASM_HEAP || "8388608", 10);
const code = fs.readFileSync(0, "utf8");
const mp = await loadMicroPython({
  heapsize,
  stdout: (s) => process.stdout.write(s + "\n"),
  stderr: (s) => process.stderr.write(s + "\n"),
});
mp.FS.mkdir("/firmware");
for (const f of fs.readdirSync(path.join(root, "firmware"))) {
  if (f.endsWith(".py")) mp.FS.writeFile("/firmware/" + f, fs.readFileSync(path.join(root, "firmware", f)));
}
try {
  mp.runPython(code);
} catch (e) {
  process.stderr.write(String(e.message || e) + "\n");
  process.exitCode = 3;
}
