// The dashboard in a real browser: headless Chromium (Debian's /usr/bin/chromium) driven by
// playwright-core.  Run by tests/test_dashboard_browser.py against `upright dashboard --virtual`:
//
//   node host/dashboard/e2e.mjs URL OUTDIR [SCREENSHOT.png]
//
// Loads the page, sees live data move, starts a recording, arms the board (state seen on the
// page), steps the reference and sees the cart follow, runs a square wave (screenshot),
// disarms (the force plot then shows 0 N: the applied force, whatever the telemetry's last force
// value), stops the recording and downloads it; then arms again and closes the page without
// disarming: the server must stop feeding and disarm by itself.  Also checked: the page sends
// this run's token with every command, and the same command from the page without it is refused.  Writes OUTDIR/page_rows.json
// (every telemetry row the page received), OUTDIR/recording.csv (the download) and prints one
// JSON line with what it saw and measured.  Exit status 0 = every step passed.
import { chromium } from "playwright-core";
import fs from "node:fs";
import path from "node:path";

const [url, outDir, shot] = process.argv.slice(2);
if (!url || !outDir) {
  console.error("usage: node e2e.mjs URL OUTDIR [SCREENSHOT.png]");
  process.exit(2);
}
fs.mkdirSync(outDir, { recursive: true });
const exe = process.env.CHROMIUM || "/usr/bin/chromium";
const result = { steps: [] };
const step = (name, extra) => { result.steps.push(name); if (extra) Object.assign(result, extra); };
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function status() {
  const r = await fetch(new URL("/api/status", url));
  return r.json();
}

async function waitStatus(pred, ms, what) {
  const t0 = Date.now();
  for (;;) {
    const s = await status();
    if (pred(s)) return [s, Date.now() - t0];
    if (Date.now() - t0 > ms) throw new Error(`timed out after ${ms} ms waiting for ${what}: ${JSON.stringify(s.heartbeat)}`);
    await sleep(50);
  }
}

const browser = await chromium.launch({
  executablePath: exe,
  headless: true,
  // no network beyond loopback here: keep Chromium from reaching out
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"],
});
let code = 0;
try {
  const context = await browser.newContext({ acceptDownloads: true, viewport: { width: 1280, height: 820 } });
  const page = await context.newPage();
  const errors = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  await page.goto(url);
  await page.waitForFunction(() => window.dash && window.dash.id && window.dash.nrows > 25, null, { timeout: 20000 });
  step("loaded");

  // the server takes commands only with this run's token (the page has it): the page's own
  // fetch without it is refused
  const noToken = await page.evaluate(async () => {
    const r = await fetch("/api/disarm", { method: "POST", headers: { "X-Upright-Page": window.dash.id }, body: "{}" });
    return { status: r.status, text: await r.text() };
  });
  if (noToken.status !== 403) throw new Error(`a command without the token got ${noToken.status}: ${noToken.text}`);
  step("token", { no_token_status: noToken.status, no_token_error: JSON.parse(noToken.text).error });

  // live data: rows keep arriving and the plots redraw
  const s0 = await status(), n0 = await page.evaluate(() => window.dash.nrows), t0 = Date.now();
  await sleep(2000);
  const s1 = await status(), n1 = await page.evaluate(() => window.dash.nrows), dt = (Date.now() - t0) / 1000;
  if (n1 - n0 < 40) throw new Error(`only ${n1 - n0} telemetry rows in 2 s`);
  step("live", { rows_per_s_page: (n1 - n0) / dt, rows_per_s_server: (s1.telemetry_rows - s0.telemetry_rows) / dt,
                 behind_s: s1.virtual ? s1.virtual.behind_s : null });

  await page.click("#recstart");
  await page.waitForFunction(() => /recording/.test(document.querySelector("#recinfo").textContent), null, { timeout: 5000 });
  step("recording");

  // arm: the page shows armed/balancing, and so does the server's view of the link
  await page.click("#arm");
  await page.waitForFunction(() => ["1", "2"].includes(document.querySelector("#state").dataset.state), null, { timeout: 5000 });
  const [armed] = await waitStatus((s) => [1, 2].includes(s.heartbeat.state), 5000, "armed on the link");
  step("armed", { armed_page: await page.textContent("#state"), armed_link: armed.heartbeat.state_name,
                  armed_fw_state: armed.virtual ? armed.virtual.fw_state : null, feeding_armed: armed.feeding });

  // reference step: the cart follows (the firmware balancing the simulated robot)
  await page.fill("#refx", "0.1");
  await page.click("#step");
  await page.waitForFunction(() => {
    const d = window.dash, C = d.columns;
    const rows = Array.from(d.received.values()).slice(-5);
    return rows.length && rows.every((r) => r[C.indexOf("x")] > 0.05);
  }, null, { timeout: 8000 });
  const tiltMax = await page.evaluate(() => {
    const d = window.dash, i = d.columns.indexOf("phi");
    return Math.max(...Array.from(d.received.values()).slice(-400).map((r) => Math.abs(r[i])));
  });
  step("moved", { tilt_max_after_step: tiltMax });

  // square wave, then a picture of the page in motion
  await page.fill("#sqamp", "0.2");
  await page.fill("#sqper", "4.4");
  await page.click("#sqstart");
  await sleep(5500);
  if (shot) {
    await page.screenshot({ path: shot });
    step("screenshot", { screenshot: shot });
  }
  await page.click("#sqstop");

  // measured on the page: screen updates per second and frame-to-screen latency (last 5 s)
  const m = await page.evaluate(() => {
    const d = window.dash, now = performance.timeOrigin + performance.now();
    const upd = d.updates.filter((t) => now - t < 5000);
    const lat = d.latency.slice(-250).slice().sort((a, b) => a - b);
    const q = (p) => lat[Math.min(lat.length - 1, Math.round(p * (lat.length - 1)))];
    return { updates_per_s: upd.length > 1 ? (upd.length - 1) / ((upd[upd.length - 1] - upd[0]) / 1000) : 0,
             latency_ms: { n: lat.length, p50: q(0.5), p95: q(0.95), max: lat[lat.length - 1] } };
  });
  const st = await status();
  step("measured", { page: m, server: st.stats });

  await page.click("#disarm");
  await page.waitForFunction(() => document.querySelector("#state").dataset.state === "0", null, { timeout: 5000 });
  const [disarmed] = await waitStatus((s) => s.heartbeat.state === 0, 5000, "disarmed on the link");
  step("disarmed", { disarmed_page: await page.textContent("#state"), disarmed_link: disarmed.heartbeat.state_name,
                     feeding_disarmed: disarmed.feeding });

  // disarmed: the force plot shows the applied force, 0, on every point drawn while not balancing
  await sleep(1000);
  const forces = await page.evaluate(() => {
    const d = window.dash, C = d.columns, b = d.drawn;
    const out = { balancing_points: 0, idle_points: 0, idle_drawn_nonzero: 0, idle_telemetry_nonzero: 0,
                  idle_telemetry_force_max: 0, balancing_drawn_equal: true };
    for (let i = 0; i < b.n.length; i++) {
      const r = d.received.get(b.n[i]);
      if (!r) continue;
      const f = r[C.indexOf("force")];
      if (r[C.indexOf("state")] === d.balancing) {
        out.balancing_points++;
        if (b.force[i] !== f) out.balancing_drawn_equal = false;
      } else {
        out.idle_points++;
        if (b.force[i] !== 0) out.idle_drawn_nonzero++;
        if (f !== 0) { out.idle_telemetry_nonzero++; out.idle_telemetry_force_max = Math.max(out.idle_telemetry_force_max, Math.abs(f)); }
      }
    }
    return out;
  });
  step("force_drawn", { force_drawn: forces });

  await page.click("#recstop");
  await page.waitForFunction(() => /recorded \d+ rows/.test(document.querySelector("#msg").textContent), null, { timeout: 5000 });
  const [download] = await Promise.all([page.waitForEvent("download"), page.click("#recdl")]);
  const csvPath = path.join(outDir, "recording.csv");
  await download.saveAs(csvPath);
  step("downloaded", { csv: csvPath, csv_name: download.suggestedFilename(), record: (await status()).record });

  const rows = await page.evaluate(() => ({ columns: window.dash.columns, rows: Array.from(window.dash.received.values()) }));
  fs.writeFileSync(path.join(outDir, "page_rows.json"), JSON.stringify(rows));

  // arm again, then close the page without disarming: the server stops feeding and disarms
  // (the pendulum, disarmed, has been falling: stand it up first, as a hand would)
  await page.click("#upright");
  await page.waitForFunction(() => /pendulum upright/.test(document.querySelector("#msg").textContent), null, { timeout: 5000 });
  await sleep(300);
  await page.click("#arm");
  await page.waitForFunction(() => ["1", "2"].includes(document.querySelector("#state").dataset.state), null, { timeout: 5000 });
  await waitStatus((s) => s.feeding && [1, 2].includes(s.heartbeat.state), 5000, "armed again");
  await page.close();
  const [gone, ms] = await waitStatus((s) => s.heartbeat.state === 0 && !s.feeding, 5000, "disarm after the page closed");
  step("closed", { disarmed_after_close_ms: ms, after_close: gone.heartbeat.state_name, notes: gone.notes });
  if (errors.length) throw new Error("page errors: " + errors.join("; "));
  result.ok = true;
} catch (e) {
  result.ok = false;
  result.error = String(e && e.stack || e);
  code = 1;
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
process.exit(code);
