// The browser's half of server/tests/status_page.rs: Playwright driving
// the system's chromium (Playwright's own browser download needs the
// internet). Usage: node status_page.mjs URL CHROMIUM SCREENSHOT.
//
// Told step by step on standard input, answering one line per step on
// standard output:
// - at once: opens URL at 1280x900 with guest's credentials, waits until
//   queue `dashboard` shows 7 ready and the charts, bars and listeners are
//   drawn, prints `dom JSON` (what the page shows, read from its DOM,
//   and in `nodes_answered` every /api/nodes answer it got),
//   saves the screenshot and prints `screenshot PATH`;
// - on `next`: waits in the same page until `dashboard` shows 12 ready,
//   prints `ready 12` and closes the browser.
import { chromium } from "playwright";
import { createInterface } from "node:readline";

const [url, executablePath, screenshot] = process.argv.slice(2);
const lines = createInterface({ input: process.stdin })[Symbol.asyncIterator]();
const ready = 'tr[data-queue="dashboard"] [data-field="ready"]';

async function waitForReady(page, value) {
  try {
    await page.waitForFunction(
      ([selector, v]) => document.querySelector(selector)?.textContent === v,
      [ready, value],
      { timeout: 30000 },
    );
  } catch (e) {
    console.error("last refresh: " + await page.textContent("#refreshed"));
    throw e;
  }
}

let closing = false;
const browser = await chromium.launch({ executablePath, args: ["--no-sandbox", "--disable-gpu"] });
try {
  const context = await browser.newContext({
    httpCredentials: { username: "guest", password: "guest" },
    viewport: { width: 1280, height: 900 },
  });
  const page = await context.newPage();
  // The page's own complaints go to standard error, for the test's message.
  page.on("pageerror", (e) => console.error("page error: " + e.message));
  page.on("console", (m) => console.error("page console: " + m.text()));
  // Every /api/nodes answer the page got, for the test to find the one
  // its bars show.
  // A body still on its way when the browser closes at the end rejects:
  // unhandled, that rejection made Node exit 1 after the test had passed
  // (seen once in CI); any other failure to read one is reported.
  const nodes = [];
  page.on("response", async (response) => {
    if (new URL(response.url()).pathname !== "/api/nodes") return;
    try {
      nodes.push((await response.json())[0]);
    } catch (e) {
      if (!closing) console.error("an /api/nodes body not read: " + e.message);
    }
  });
  await page.goto(url);
  await waitForReady(page, "7");
  await page.waitForFunction(() =>
    document.getElementById("alarms").className !== "muted" &&
    document.getElementById("headroom-fds").dataset.limit &&
    document.querySelectorAll("#listeners tbody tr").length > 0 &&
    Number(document.querySelector('#chart-rates polyline[data-series="publish"]')?.dataset.count) >= 2,
    null, { timeout: 30000 });
  const dom = await page.evaluate(() => {
    const card = (id) => {
      const c = document.getElementById(id);
      return {
        used: c.dataset.used, limit: c.dataset.limit,
        width: c.querySelector(".fill").style.width,
        text: c.querySelector(".figure").textContent,
      };
    };
    const series = (chart, legend) => Object.fromEntries(
      [...document.querySelectorAll(`#${chart} polyline`)].map((line) => {
        const entry = document.querySelector(`#${legend} [data-series="${line.dataset.series}"]`);
        return [line.dataset.series, {
          count: Number(line.dataset.count),
          points: line.getAttribute("points").split(" ").filter(Boolean).length,
          newest: entry.dataset.newest, value: entry.dataset.value, legend: entry.textContent,
        }];
      }));
    return {
      alarms: [document.getElementById("alarms").className, document.getElementById("alarms").textContent],
      connections: document.getElementById("t-connections").textContent,
      sparklines: document.querySelectorAll("svg.spark").length,
      headroom: {
        memory: card("headroom-memory"), disk: card("headroom-disk"), fds: card("headroom-fds"),
      },
      listeners: [...document.querySelectorAll("#listeners tbody tr")].map(
        (row) => [...row.cells].map((cell) => cell.textContent)),
      rates: series("chart-rates", "legend-rates"),
      lengths: series("chart-lengths", "legend-lengths"),
      axis_labels: [...document.querySelectorAll("#chart-rates text")].map((t) => t.textContent),
      links: [...document.querySelectorAll("a[href]")].map((a) => a.getAttribute("href")),
      size: [window.innerWidth, window.innerHeight],
    };
  });
  // The body of an answer the page has drawn may still be on its way here.
  await page.waitForTimeout(1000);
  dom.nodes_answered = nodes;
  console.log("dom " + JSON.stringify(dom));
  await page.screenshot({ path: screenshot });
  console.log("screenshot " + screenshot);
  const told = await lines.next();
  if (told.value !== "next") throw new Error("expected `next`, got " + JSON.stringify(told.value));
  await waitForReady(page, "12");
  console.log("ready 12");
} finally {
  closing = true;
  await browser.close();
}
process.exit(0);
