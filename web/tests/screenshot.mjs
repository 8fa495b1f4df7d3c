// Opens one of omniscan's pages in headless Chromium (Debian's, through
// playwright-core), waits until the viewer has drawn, applies the options
// and writes a screenshot, then prints what a test asserts on as JSON:
// console errors, page errors, any request that would leave the page
// (anything not file:, data: or blob:), and the viewer's state.
//
//   node web/tests/screenshot.mjs PAGE.html OUT.png [--width W] [--height H]
//     [--camera JSON] [--background r,g,b] [--show 0,1] [--markers on|off]
import { chromium } from "playwright-core";
import path from "node:path";

const [page_file, out, ...rest] = process.argv.slice(2);
const options = { width: 640, height: 480, markers: "on" };
for (let i = 0; i < rest.length; i += 2) options[rest[i].replace(/^--/, "")] = rest[i + 1];

const browser = await chromium.launch({
  executablePath: process.env.OMNISCAN_CHROMIUM || "/usr/bin/chromium",
  args: [
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
  ],
});
const report = { consoleErrors: [], pageErrors: [], externalRequests: [] };
try {
  const context = await browser.newContext({
    viewport: { width: Number(options.width), height: Number(options.height) },
    deviceScaleFactor: 1,
  });
  const page = await context.newPage();
  page.on("console", (m) => m.type() === "error" && report.consoleErrors.push(m.text()));
  // Long tasks (over 50 ms on the main thread) are what freezes a page.
  await page.addInitScript(() => {
    window.__longTasks = [];
    new PerformanceObserver((list) => {
      for (const e of list.getEntries()) window.__longTasks.push(e.duration);
    }).observe({ type: "longtask", buffered: true });
  });
  page.on("pageerror", (e) => report.pageErrors.push(String(e)));
  await page.route("**/*", (route) => {
    const url = route.request().url();
    if (/^(file|data|blob):/.test(url)) return route.continue();
    report.externalRequests.push(url);
    return route.abort();
  });
  const start = Date.now();
  await page.goto("file://" + path.resolve(page_file));
  await page.waitForFunction(() => window.omniscanViewer && (window.omniscanViewer.loaded || window.omniscanViewer.error), null, { timeout: 300000 });
  report.loadMs = Date.now() - start;
  await page.evaluate(async (o) => {
    const v = window.omniscanViewer;
    if (v.error) return;
    if (o.show) v.show(o.show.split(",").map(Number));
    if (o.background) v.setBackground(o.background.split(",").map(Number));
    if (o.camera) v.setCamera(JSON.parse(o.camera));
    v.setMarkersVisible(o.markers !== "off");
    // Spark sorts in a worker: give it frames to settle after a change.
    const start = v.framesDrawn;
    await new Promise((resolve) => {
      const wait = () => (v.framesDrawn - start >= 20 ? resolve() : requestAnimationFrame(wait));
      wait();
    });
  }, options);
  // A clip of the page rather than the element: the element's screenshot
  // waits for it to be "stable", which a canvas that redraws every frame
  // is not when frames are slow (a million splats on SwiftShader).
  // In a report the viewer is further down the page: scroll it into view
  // and keep the clip inside the viewport.
  const canvas = page.locator("#omniscan-viewer .ov-canvas canvas");
  await canvas.evaluate((c) => c.scrollIntoView({ block: "start" }));
  const box = await canvas.boundingBox();
  const view = page.viewportSize();
  const clip = {
    x: Math.max(0, box.x),
    y: Math.max(0, box.y),
    width: Math.min(box.width, view.width - Math.max(0, box.x)),
    height: Math.min(box.height, view.height - Math.max(0, box.y)),
  };
  await page.screenshot({ path: out, clip, timeout: 300000 });
  Object.assign(report, await page.evaluate(() => {
    const v = window.omniscanViewer;
    const c = document.querySelector("#omniscan-viewer .ov-canvas canvas");
    const tasks = window.__longTasks || [];
    return {
      loaded: v.loaded, error: v.error, framesDrawn: v.framesDrawn, canvas: [c.width, c.height],
      longTasks: tasks.length, longestTaskMs: tasks.length ? Math.max(...tasks) : 0,
    };
  }));
} finally {
  await browser.close();
}
console.log(JSON.stringify(report));
