'use strict';
// Scenario harness for the JavaScript driver (same protocol as python/harness.py):
//   node main.js --list
//   node main.js --url URL --prefix P [--only a,b]
// prints {"start": name} then one result record per scenario.

const registry = [];

function scenario(name, fn) {
  registry.push([`amqplib.${name}`, fn]);
}

class Failure extends Error {}

function replyName(text) {
  if (text == null) return null;
  return String(text).split(' - ')[0].trim();
}

function plain(v) {
  if (Buffer.isBuffer(v)) {
    const s = v.toString('utf8');
    return Buffer.from(s, 'utf8').equals(v) ? { bytes: s } : { hex: v.toString('hex') };
  }
  if (Array.isArray(v)) return v.map(plain);
  if (v && typeof v === 'object') {
    const out = {};
    for (const k of Object.keys(v).sort()) out[k] = plain(v[k]);
    return out;
  }
  if (typeof v === 'bigint') return Number(v);
  return v === undefined ? null : v;
}

function same(a, b) {
  return JSON.stringify(plain(a)) === JSON.stringify(plain(b));
}

class T {
  constructor(url, prefix, http) {
    this.url = url;
    this.prefix = prefix;
    // The broker's management API (`--http`), for suites that change
    // policies or read listings as an operator would.
    this.http = http;
    this.observations = [];
    this.cleanups = [];
    const u = new URL(url);
    this.host = u.hostname || '127.0.0.1';
    this.port = Number(u.port || 5672);
    this.user = decodeURIComponent(u.username || 'guest');
    this.password = decodeURIComponent(u.password || 'guest');
    const p = u.pathname.replace(/^\//, '');
    this.vhost = p ? decodeURIComponent(p) : '/';
  }
  n(name) { return `${this.prefix}${name}`; }
  urlWith({ user, password, vhost, query } = {}) {
    const e = encodeURIComponent;
    return `amqp://${e(user ?? this.user)}:${e(password ?? this.password)}@${this.host}:${this.port}/${e(vhost ?? this.vhost)}${query ? '?' + query : ''}`;
  }
  obs(label, value) { this.observations.push([label, plain(value === undefined ? null : value)]); return value; }
  eq(label, actual, expected) {
    this.obs(label, actual);
    if (!same(actual, expected)) {
      throw new Failure(`${label}: expected ${JSON.stringify(plain(expected))}, got ${JSON.stringify(plain(actual))}`);
    }
    return actual;
  }
  check(cond, msg) { if (!cond) throw new Failure(msg); }
  defer(fn) { this.cleanups.push(fn); }
  async runCleanups() {
    for (const fn of this.cleanups.reverse()) {
      try { await fn(); } catch (e) { /* ignore */ }
    }
  }
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// How long a scenario waits for something it expects: a hang limit, generous
// enough for a loaded CI machine (the wait ends as soon as the thing happens).
const HANG_MS = 30000;

async function waitUntil(pred, timeout = HANG_MS, what = 'condition') {
  const deadline = Date.now() + timeout;
  while (Date.now() < deadline) {
    if (await pred()) return true;
    await sleep(20);
  }
  throw new Failure(`timed out after ${timeout}ms waiting for ${what}`);
}

async function main() {
  const argv = process.argv.slice(2);
  const arg = (k, d) => { const i = argv.indexOf(k); return i >= 0 ? argv[i + 1] : d; };
  if (argv.includes('--list')) {
    for (const [name] of registry) console.log(name);
    return;
  }
  const url = arg('--url');
  const prefix = arg('--prefix', 'cf-');
  const only = new Set((arg('--only', '') || '').split(',').filter(Boolean));
  for (const [name, fn] of registry) {
    if (only.size && !only.has(name)) continue;
    console.log(JSON.stringify({ start: name }));
    const t = new T(url, prefix, arg('--http'));
    const started = Date.now();
    let ok = true;
    let error = null;
    try {
      await Promise.race([
        fn(t),
        sleep(60000).then(() => { throw new Failure('scenario timed out after 60s'); }),
      ]);
    } catch (e) {
      ok = false;
      const where = (e && e.stack ? e.stack.split('\n').find((l) => l.includes('scenarios.js')) : '') || '';
      error = `${e && e.constructor ? e.constructor.name : 'Error'}: ${e && e.message ? e.message : e} ${where.trim()}`.trim();
    }
    await t.runCleanups();
    console.log(JSON.stringify({ name, ok, error, obs: t.observations, ms: Date.now() - started }));
  }
}

module.exports = { scenario, Failure, replyName, T, sleep, waitUntil, main, plain, HANG_MS };
