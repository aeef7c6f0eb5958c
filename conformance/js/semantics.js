'use strict';
// RabbitMQ's semantics driven by amqplib (issue 30): the `semantics` suite
// (lib/semantics.py) loads semantics/definitions.json into a RabbitMQ 3.10
// node and a Leveret and runs these against both (`main.js --semantics`),
// with the broker's management API (`t.http`) for what an operator does
// meanwhile. The same steps as python/s_semantics.py, with amqplib's
// encodings (its numbers in field tables) and its own consumer handling:
// policies from the definitions, a live change that drops and one that
// dead-letters a queue's head, operator policies, single active consumer
// hand-over on cancel, channel close and a killed process, consumer
// priorities with credit, argument equivalence both ways, refused
// arguments.

const amqp = require('amqplib');
const { spawn } = require('child_process');
const { scenario, Failure, replyName, sleep, waitUntil, HANG_MS } = require('./harness');

// helpers ------------------------------------------------------------------

async function connect(t) {
  const c = await amqp.connect(t.url);
  c.on('error', () => {});
  t.defer(() => c.close());
  return c;
}

async function chan(c, confirm = false) {
  const ch = confirm ? await c.createConfirmChannel() : await c.createChannel();
  ch.on('error', () => {});
  return ch;
}

async function http(t, method, path, body) {
  const auth = Buffer.from(`${t.user}:${t.password}`).toString('base64');
  const answer = await fetch(t.http + path, {
    method,
    headers: { Authorization: `Basic ${auth}`, 'Content-Type': 'application/json' },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const text = await answer.text();
  let parsed = null;
  try { parsed = text ? JSON.parse(text) : null; } catch (e) { /* not JSON */ }
  return [answer.status, parsed];
}

const q_ = encodeURIComponent;
const escape = (s) => s.replace(/[.*+?^${}()|[\]\\-]/g, '\\$&');
const ownPattern = (t, stem) => '^' + escape(t.n(stem));

async function setPolicy(t, name, pattern, definition, kind = 'policies') {
  const [status] = await http(t, 'PUT', `/api/${kind}/%2F/${q_(name)}`,
    { pattern, definition, 'apply-to': 'queues', priority: 0 });
  t.defer(() => http(t, 'DELETE', `/api/${kind}/%2F/${q_(name)}`));
  return status;
}

// The queue's policy fields once it is listed with them (RabbitMQ lists
// them from its statistics, which the suite's node emits every 100 ms) and
// `until(listed)` holds. RabbitMQ lists "no policy" as "", null or an empty
// list depending on the field; an operator reads each as none.
async function listing(t, q, until) {
  const none = (v) => (v === '' || v === null || v === undefined || (Array.isArray(v) && !v.length)
    || (typeof v === 'object' && v !== null && !Object.keys(v).length) ? null : v);
  let found = null;
  await waitUntil(async () => {
    const [status, body] = await http(t, 'GET', `/api/queues/%2F/${q_(q)}`);
    if (status !== 200 || !body || !('policy' in body)) return false;
    found = {
      policy: none(body.policy),
      operator_policy: none(body.operator_policy),
      effective_policy_definition: none(body.effective_policy_definition),
    };
    return !until || until(found);
  }, HANG_MS, `${q} listed`);
  return found;
}

async function count(c, q) {
  const ch = await chan(c);
  const ok = await ch.checkQueue(q);
  await ch.close();
  return ok.messageCount;
}

async function settledCount(c, q, want) {
  const deadline = Date.now() + HANG_MS;
  for (;;) {
    const n = await count(c, q);
    if (n === want || Date.now() > deadline) return n;
    await sleep(20);
  }
}

async function publish(ch, q, bodies) {
  for (const b of bodies) ch.sendToQueue(q, Buffer.from(String(b)), { persistent: true });
  await ch.waitForConfirms();
}

async function getAll(ch, q) {
  const out = [];
  for (;;) {
    const m = await ch.get(q, { noAck: true });
    if (!m) return out;
    out.push(m.content.toString());
  }
}

const range = (a, b) => Array.from({ length: b - a }, (_, i) => a + i);

function refusal(e) {
  const text = String(e && e.message);
  const name = /with message "([A-Z_]+)/.exec(text);
  const arg = /'(x-[a-z-]+)'|(x-[a-z-]+)/.exec(text.replace(/^[^"]*"/, ''));
  return [e && e.code, name ? name[1] : replyName(text), arg ? (arg[1] || arg[2]) : null];
}

async function declareOutcome(c, q, options) {
  const ch = await chan(c);
  try {
    await ch.assertQueue(q, options);
  } catch (e) {
    return refusal(e);
  }
  await ch.close();
  return 'ok';
}

function tidy(t, c, names) {
  t.defer(async () => {
    const ch = await chan(c);
    for (const q of names) await ch.deleteQueue(q);
  });
}

// policies -----------------------------------------------------------------------

scenario('policy.from_definitions', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const stems = ['x.pol-maxlen2', 'x.pol-prio', 'x.pol-prio-high', 'x.pol-lazy', 'x.pol-none'];
  tidy(t, c, stems.map((s) => t.n(s)));
  for (const stem of stems) {
    await ch.assertQueue(t.n(stem), { durable: false });
    await publish(ch, t.n(stem), range(1, 7));
  }
  for (const stem of stems) {
    t.obs(`${stem} ready`, await count(c, t.n(stem)));
    t.obs(`${stem} listed`, await listing(t, t.n(stem)));
  }
  t.eq('maxlen2 kept the newest', await getAll(ch, t.n('x.pol-maxlen2')), ['5', '6']);
});

scenario('policy.live_change_drops_the_head', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = t.n('live.q');
  tidy(t, c, [q]);
  await ch.assertQueue(q, { durable: false });
  await publish(ch, q, range(1, 7));
  t.eq('status class', Math.floor(await setPolicy(t, t.n('live'), ownPattern(t, 'live.'), { 'max-length': 2 }) / 100), 2);
  t.eq('shortened at once', await settledCount(c, q, 2), 2);
  t.obs('listed', await listing(t, q, (found) => found.policy === t.n('live')));
  await http(t, 'DELETE', `/api/policies/%2F/${q_(t.n('live'))}`);
  await listing(t, q, (found) => found.policy === null);
  await publish(ch, q, range(7, 10));
  t.eq('grows again once cleared', await getAll(ch, q), ['5', '6', '7', '8', '9']);
});

scenario('policy.live_change_dead_letters_the_head', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = t.n('livedl.q');
  const dlx = t.n('livedl-x');
  const dead = t.n('livedl-dead');
  tidy(t, c, [q, dead]);
  await ch.assertExchange(dlx, 'fanout', { durable: false });
  t.defer(() => http(t, 'DELETE', `/api/exchanges/%2F/${q_(dlx)}`));
  await ch.assertQueue(dead, { durable: false });
  await ch.bindQueue(dead, dlx, '');
  await ch.assertQueue(q, { durable: false });
  await publish(ch, q, range(1, 6));
  await setPolicy(t, t.n('livedl'), ownPattern(t, 'livedl.q'), { 'max-length': 1, 'dead-letter-exchange': dlx });
  t.eq('dead-lettered at once', await settledCount(c, dead, 4), 4);
  const got = [];
  for (;;) {
    const m = await ch.get(dead, { noAck: true });
    if (!m) break;
    const death = ((m.properties.headers || {})['x-death'] || [{}])[0];
    got.push([m.content.toString(), death.reason, String(death.queue).replace(t.prefix, '~')]);
  }
  t.eq('the head, in order, with x-death', got, range(1, 5).map((i) => [String(i), 'maxlen', '~livedl.q']));
  t.eq('the queue keeps the newest', await getAll(ch, q), ['5']);
});

scenario('operator_policy.the_stricter_value_wins', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const cases = { 'z.op-plain': {}, 'z.op-arg2': { 'x-max-length': 2 }, 'z.op-arg10': { 'x-max-length': 10 } };
  tidy(t, c, Object.keys(cases).map((s) => t.n(s)));
  for (const [stem, args] of Object.entries(cases)) {
    await ch.assertQueue(t.n(stem), { durable: false, arguments: args });
    await publish(ch, t.n(stem), range(1, 9));
    t.obs(`${stem} ready`, await count(c, t.n(stem)));
    t.obs(`${stem} listed`, await listing(t, t.n(stem)));
  }
});

scenario('operator_policy.live_changes', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = t.n('liveop.q');
  tidy(t, c, [q]);
  await ch.assertQueue(q, { durable: false });
  await publish(ch, q, range(1, 6));
  await setPolicy(t, t.n('liveop-user'), ownPattern(t, 'liveop.'), { 'max-length': 4 });
  t.eq("the policy's 4", await settledCount(c, q, 4), 4);
  await setPolicy(t, t.n('liveop'), ownPattern(t, 'liveop.'), { 'max-length': 1 }, 'operator-policies');
  t.eq("the operator policy's stricter 1", await settledCount(c, q, 1), 1);
  t.obs('listed', await listing(t, q, (found) => found.operator_policy === t.n('liveop')));
});

// single active consumer ----------------------------------------------------------

async function consumersListed(t, q) {
  let found = [];
  await waitUntil(async () => {
    const [status, body] = await http(t, 'GET', '/api/consumers/%2F');
    const mine = status === 200 ? (body || []).filter((x) => x.queue && x.queue.name === q) : [];
    found = mine.map((x) => [x.consumer_tag, x.active, x.activity_status]).sort();
    return found.length === 2;
  }, HANG_MS, 'both consumers listed');
  return found;
}

async function sacQueue(t, c, ch, stem) {
  const q = t.n(stem);
  tidy(t, c, [q]);
  await ch.assertQueue(q, { durable: false, arguments: { 'x-single-active-consumer': true } });
  return q;
}

scenario('sac.cancel_hands_over', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await sacQueue(t, c, ch, 'sac-cancel');
  const first = await chan(c);
  await first.prefetch(2);
  const got1 = [];
  await first.consume(q, (m) => got1.push(m), { consumerTag: 'first' });
  const second = await chan(c);
  const got2 = [];
  await second.consume(q, (m) => got2.push([m.content.toString(), m.fields.redelivered]), { noAck: true, consumerTag: 'second' });
  await publish(ch, q, range(1, 7));
  await waitUntil(() => got1.length === 2, HANG_MS, "the active consumer's share");
  await sleep(200);
  t.eq('the first is active, the second waits', await consumersListed(t, q),
    [['first', true, 'single_active'], ['second', false, 'waiting']]);
  t.eq('waiting share', got2, []);
  await first.cancel('first');
  // Nothing while the cancelled consumer holds two unacked (see
  // python/s_semantics.py's sac.cancel_hands_over).
  await sleep(1000);
  t.obs("the next one's share a second after the cancel", got2);
  for (const m of got1) first.ack(m);
  await first.close();
  await waitUntil(() => got2.length === 4, HANG_MS, 'the hand-over');
  t.eq('hand-over: the rest, not what the first held', got2, range(3, 7).map((i) => [String(i), false]));
  t.eq('nothing left', await count(c, q), 0);
});

scenario('sac.channel_close_hands_over', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await sacQueue(t, c, ch, 'sac-close');
  const other = await connect(t);
  const first = await chan(other);
  await first.prefetch(2);
  const got1 = [];
  await first.consume(q, (m) => got1.push(m.content.toString()), { consumerTag: 'first' });
  const second = await chan(c);
  const got2 = [];
  await second.consume(q, (m) => got2.push([m.content.toString(), m.fields.redelivered]), { noAck: true, consumerTag: 'second' });
  await publish(ch, q, range(1, 7));
  await waitUntil(() => got1.length === 2, HANG_MS, "the active consumer's share");
  await sleep(200);
  t.eq('waiting share', got2, []);
  await first.close();
  await waitUntil(() => got2.length === 6, HANG_MS, 'the hand-over');
  t.eq('hand-over: the unacked first, redelivered, then the rest', got2,
    [['1', true], ['2', true], ...range(3, 7).map((i) => [String(i), false])]);
});

const CHILD = `
const amqp = require('amqplib');
(async () => {
  const c = await amqp.connect(process.argv[1]);
  const ch = await c.createChannel();
  await ch.prefetch(2);
  let n = 0;
  await ch.consume(process.argv[2], () => { n += 1; if (n === 2) console.log('held 2'); }, { consumerTag: 'doomed' });
  console.log('consuming');
})();
`;

function lines(child) {
  const queue = [];
  const waiters = [];
  let buffer = '';
  child.stdout.on('data', (data) => {
    buffer += data;
    let at;
    while ((at = buffer.indexOf('\n')) >= 0) {
      const line = buffer.slice(0, at);
      buffer = buffer.slice(at + 1);
      if (waiters.length) waiters.shift()(line); else queue.push(line);
    }
  });
  return () => (queue.length ? Promise.resolve(queue.shift()) : new Promise((r) => waiters.push(r)));
}

scenario('sac.killed_connection_hands_over', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await sacQueue(t, c, ch, 'sac-kill');
  const child = spawn(process.execPath, ['-e', CHILD, t.url, q], { cwd: __dirname, stdio: ['ignore', 'pipe', 'inherit'] });
  t.defer(() => child.kill('SIGKILL'));
  const next = lines(child);
  t.eq('child', await Promise.race([next(), sleep(HANG_MS).then(() => 'timeout')]), 'consuming');
  const second = await chan(c);
  const got2 = [];
  await second.consume(q, (m) => got2.push([m.content.toString(), m.fields.redelivered]), { noAck: true, consumerTag: 'survivor' });
  t.eq('the killed one was active', await consumersListed(t, q),
    [['doomed', true, 'single_active'], ['survivor', false, 'waiting']]);
  await publish(ch, q, range(1, 7));
  t.eq('child', await Promise.race([next(), sleep(HANG_MS).then(() => 'timeout')]), 'held 2');
  await sleep(200);
  t.eq('waiting share while the first lives', got2, []);
  const exited = new Promise((r) => child.once('exit', r));
  child.kill('SIGKILL');
  await exited;
  await waitUntil(() => got2.length === 6, HANG_MS, 'the hand-over');
  t.eq('hand-over: the unacked first, redelivered, then the rest', got2,
    [['1', true], ['2', true], ...range(3, 7).map((i) => [String(i), false])]);
});

// consumer priorities ----------------------------------------------------------------

scenario('consumer_priority.served_while_it_has_credit', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = (await ch.assertQueue('', { exclusive: true })).queue;
  const got = { low: [], high: [] };
  const chans = {};
  for (const [name, priority, prefetch] of [['low', 1, 10], ['high', 5, 2]]) {
    const x = await chan(c);
    await x.prefetch(prefetch);
    await x.consume(q, (m) => got[name].push(m), { priority });
    chans[name] = x;
  }
  const bodies = (name) => got[name].map((m) => m.content.toString());
  await publish(ch, q, range(1, 5));
  await waitUntil(() => got.low.length + got.high.length === 4, HANG_MS, 'four deliveries');
  await sleep(200);
  t.eq('high while it has credit, then low', [bodies('high'), bodies('low')], [['1', '2'], ['3', '4']]);
  chans.high.ack(got.high[0]);
  await sleep(200);
  await publish(ch, q, [5]);
  await waitUntil(() => got.low.length + got.high.length === 5, HANG_MS, 'the fifth');
  await sleep(200);
  t.eq('credit back: high again', [bodies('high'), bodies('low')], [['1', '2', '5'], ['3', '4']]);
});

// argument equivalence -------------------------------------------------------------------

scenario('equivalence.definitions_queue_redeclared', async (t) => {
  const c = await connect(t);
  const same = {
    'x-message-ttl': 60000, 'x-expires': 86400000, 'x-max-length': 10, 'x-max-length-bytes': 1048576,
    'x-max-priority': 5, 'x-overflow': 'reject-publish',
    'x-dead-letter-exchange': 'sem.defs.dlx', 'x-dead-letter-routing-key': 'dead',
  };
  t.obs('identical', await declareOutcome(c, 'sem.defs.args', { durable: true, arguments: same }));
  // amqplib's own options for the same arguments.
  t.obs('as amqplib options', await declareOutcome(c, 'sem.defs.args', {
    durable: true, messageTtl: 60000, expires: 86400000, maxLength: 10, maxPriority: 5,
    deadLetterExchange: 'sem.defs.dlx', deadLetterRoutingKey: 'dead',
    arguments: { 'x-max-length-bytes': 1048576, 'x-overflow': 'reject-publish' },
  }));
  for (const [key, value] of [['x-message-ttl', 60001], ['x-max-priority', 6], ['x-overflow', 'drop-head']]) {
    t.obs(`${key}=${value}`, await declareOutcome(c, 'sem.defs.args', { durable: true, arguments: { ...same, [key]: value } }));
  }
  t.obs('sac true', await declareOutcome(c, 'sem.defs.sac', { durable: true, arguments: { 'x-single-active-consumer': true } }));
  t.obs('sac false', await declareOutcome(c, 'sem.defs.sac', { durable: true, arguments: { 'x-single-active-consumer': false } }));
});

scenario('equivalence.client_and_api_each_way', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const byClient = t.n('eq.client');
  const byApi = t.n('eq.api');
  tidy(t, c, [byClient, byApi]);
  const args = { 'x-message-ttl': 1000, 'x-max-length': 7, 'x-max-priority': 3 };
  await ch.assertQueue(byClient, { durable: true, arguments: args });
  const put = async (q, a) => Math.floor((await http(t, 'PUT', `/api/queues/%2F/${q_(q)}`,
    { durable: true, auto_delete: false, arguments: a }))[0] / 100);
  t.obs('API, same arguments', await put(byClient, args));
  t.obs('API, another ttl', await put(byClient, { ...args, 'x-message-ttl': 2000 }));
  t.obs('API creates', await put(byApi, args));
  t.obs('client, same', await declareOutcome(c, byApi, { durable: true, arguments: args }));
  t.obs('client, another max-length', await declareOutcome(c, byApi, { durable: true, arguments: { ...args, 'x-max-length': 8 } }));
});

// refused arguments ---------------------------------------------------------------------------

const REFUSED_QUEUE_ARGUMENTS = [
  ['x-delivery-limit on a classic queue', { 'x-delivery-limit': 5 }],
  ['x-max-age on a classic queue', { 'x-max-age': '1D' }],
  ['x-stream-max-segment-size-bytes on a classic queue', { 'x-stream-max-segment-size-bytes': 1000 }],
  ['x-quorum-initial-group-size on a classic queue', { 'x-quorum-initial-group-size': 3 }],
  ['x-max-in-memory-length on a classic queue', { 'x-max-in-memory-length': 10 }],
  ['x-dead-letter-strategy on a classic queue', { 'x-dead-letter-strategy': 'at-least-once' }],
  ['x-queue-mode unknown', { 'x-queue-mode': 'speedy' }],
  ['x-queue-mode lazy (accepted)', { 'x-queue-mode': 'lazy' }],
  ['x-queue-version 2 (accepted)', { 'x-queue-version': 2 }],
  ['x-overflow unknown', { 'x-overflow': 'drop-tail' }],
  ['x-max-priority 256', { 'x-max-priority': 256 }],
  ['x-message-ttl -1', { 'x-message-ttl': -1 }],
  ['x-message-ttl as text', { 'x-message-ttl': '100' }],
  ['x-expires 0', { 'x-expires': 0 }],
  ['x-max-length -1', { 'x-max-length': -1 }],
  ['x-single-active-consumer as text', { 'x-single-active-consumer': 'yes' }],
  ['x-dead-letter-routing-key without an exchange', { 'x-dead-letter-routing-key': 'k' }],
];

scenario('refused.queue_arguments', async (t) => {
  const c = await connect(t);
  const created = [];
  tidy(t, c, created);
  for (const [i, [label, args]] of REFUSED_QUEUE_ARGUMENTS.entries()) {
    const q = t.n(`refused.${i}`);
    const outcome = await declareOutcome(c, q, { durable: false, arguments: args });
    if (outcome === 'ok') created.push(q);
    t.obs(label, outcome);
  }
});

scenario('refused.consumer_priority_as_text', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = (await ch.assertQueue('', { exclusive: true })).queue;
  const x = await chan(c);
  try {
    await x.consume(q, () => {}, { arguments: { 'x-priority': 'high' } });
    t.obs('x-priority as text', 'ok');
  } catch (e) {
    t.obs('x-priority as text', refusal(e));
  }
});

module.exports = { Failure };
