'use strict';
// Scenarios driven by amqplib (Node), the standard JavaScript client.

const amqp = require('amqplib');
const { scenario, Failure, replyName, sleep, waitUntil, HANG_MS } = require('./harness');

// helpers ------------------------------------------------------------------

async function connect(t, url, opts) {
  const c = await amqp.connect(url || t.url, opts);
  c.on('error', () => {});
  t.defer(() => c.close());
  return c;
}

async function chan(c, confirm = false) {
  const ch = confirm ? await c.createConfirmChannel() : await c.createChannel();
  ch.on('error', () => {});
  return ch;
}

function errInfo(e) {
  const m = /with message "([A-Z_]+)/.exec(String(e && e.message));
  return [e && e.code, m ? m[1] : replyName(e && e.message)];
}

async function channelError(t, label, fn, code) {
  try {
    await fn();
  } catch (e) {
    const info = errInfo(e);
    t.obs(label, info);
    if (info[0] !== code) throw new Failure(`${label}: expected ${code}, got ${e.code} ${e.message}`);
    return;
  }
  throw new Failure(`${label}: expected channel error ${code}, call succeeded`);
}

function closedWith(emitter) {
  return new Promise((resolve) => emitter.once('error', resolve));
}

async function within(p, ms, what) {
  return Promise.race([p, sleep(ms).then(() => { throw new Failure(`timed out waiting for ${what}`); })]);
}

async function getAll(ch, q) {
  const out = [];
  for (;;) {
    const m = await ch.get(q, { noAck: true });
    if (!m) return out;
    out.push(m.content.toString());
  }
}

async function tempQueue(ch, args = {}) {
  return (await ch.assertQueue('', { exclusive: true, ...args })).queue;
}

function collector(n) {
  const got = [];
  let resolve;
  const done = new Promise((r) => { resolve = r; });
  const push = (m) => { got.push(m); if (got.length >= n) resolve(got); };
  return { got, push, done };
}

async function handshakeRefusal(t, url, opts) {
  try {
    const c = await amqp.connect(url, opts);
    await c.close();
  } catch (e) {
    const m = /(\d{3}) \(([A-Z-]+)\)/.exec(String(e.message));
    if (m) return [Number(m[1]), m[2].replace(/-/g, '_')];
    throw new Failure(`no connection.close from the broker: ${e.message}`);
  }
  throw new Failure('connection succeeded');
}

// negotiation and auth --------------------------------------------------------

scenario('connection.amqplain', async (t) => {
  const c = await connect(t, t.url, { credentials: amqp.credentials.amqplain(t.user, t.password) });
  const ch = await chan(c);
  const q = await tempQueue(ch);
  t.eq('declared over AMQPLAIN login', q.startsWith('amq.gen-'), true);
});

scenario('connection.amqplain_bad_password', async (t) => {
  t.eq('refusal', await handshakeRefusal(t, t.url, { credentials: amqp.credentials.amqplain(t.user, 'wrong') }), [403, 'ACCESS_REFUSED']);
});

scenario('connection.plain_bad_password', async (t) => {
  t.eq('refusal', await handshakeRefusal(t, t.urlWith({ password: 'wrong' })), [403, 'ACCESS_REFUSED']);
});

scenario('connection.unknown_vhost', async (t) => {
  // amqplib reports a close during connection.open without its code.
  try {
    const c = await amqp.connect(t.urlWith({ vhost: 'no-such-vhost' }));
    await c.close();
  } catch (e) {
    t.eq('connection.close instead of open-ok', /got <ConnectionClose/.test(e.message), true);
    return;
  }
  throw new Failure('connection to an unknown vhost succeeded');
});

scenario('connection.server_properties', async (t) => {
  const c = await connect(t);
  const props = c.connection.serverProperties;
  for (const cap of ['publisher_confirms', 'exchange_exchange_bindings', 'basic.nack', 'consumer_cancel_notify', 'authentication_failure_close', 'per_consumer_qos']) {
    t.eq(`capability ${cap}`, props.capabilities[cap], true);
  }
});

scenario('connection.heartbeat', async (t) => {
  const c = await connect(t, t.urlWith({ query: 'heartbeat=1' }));
  t.eq('negotiated heartbeat', c.connection.heartbeat, 1);
  let closed = null;
  c.on('close', (e) => { closed = e || 'closed'; });
  await sleep(3500);
  t.eq('connection survived idle period', closed, null);
  const ch = await chan(c);
  const q = await tempQueue(ch);
  ch.sendToQueue(q, Buffer.from('after idle'));
  await waitUntil(async () => (await ch.checkQueue(q)).messageCount === 1);
  t.eq('message', (await ch.get(q, { noAck: true })).content.toString(), 'after idle');
});

scenario('connection.frame_max_4096', async (t) => {
  const c = await connect(t, t.urlWith({ query: 'frameMax=4096' }));
  t.eq('negotiated frame max', c.connection.frameMax, 4096);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  const body = Buffer.alloc(70000, 7);
  body.write('start');
  ch.sendToQueue(q, body);
  await ch.waitForConfirms();
  const m = await ch.get(q, { noAck: true });
  t.eq('body intact', m.content.equals(body), true);
});

scenario('connection.many_channels', async (t) => {
  const c = await connect(t);
  const chans = [];
  for (let i = 0; i < 100; i++) chans.push(await chan(c));
  const q = await tempQueue(chans[0]);
  chans.forEach((ch, i) => ch.sendToQueue(q, Buffer.from(String(i))));
  await waitUntil(async () => (await chans[99].checkQueue(q)).messageCount === 100);
  const bodies = (await getAll(chans[50], q)).map(Number).sort((a, b) => a - b);
  t.eq('one message per channel', bodies, [...Array(100).keys()]);
  await Promise.all(chans.slice(1).map((ch) => ch.close()));
  t.eq('first still usable', (await chans[0].checkQueue(q)).messageCount, 0);
});

// exchanges --------------------------------------------------------------------

scenario('exchange.topic', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const ex = t.n('js-topic');
  t.defer(() => ch.deleteExchange(ex));
  await ch.assertExchange(ex, 'topic', { durable: false });
  const binds = { 'stock.#': null, '*.nyse.*': null, 'stock.*.ibm': null, '#.ibm': null };
  const qs = {};
  for (const k of Object.keys(binds)) {
    qs[k] = await tempQueue(ch);
    await ch.bindQueue(qs[k], ex, k);
  }
  for (const key of ['stock.nyse.ibm', 'stock.nasdaq.msft', 'bond.nyse.x', 'ibm', 'stock']) {
    ch.publish(ex, key, Buffer.from(key));
  }
  await ch.waitForConfirms();
  const got = {};
  for (const k of Object.keys(qs)) got[k] = await getAll(ch, qs[k]);
  t.eq('routing', got, {
    'stock.#': ['stock.nyse.ibm', 'stock.nasdaq.msft', 'stock'],
    '*.nyse.*': ['stock.nyse.ibm', 'bond.nyse.x'],
    'stock.*.ibm': ['stock.nyse.ibm'],
    '#.ibm': ['stock.nyse.ibm', 'ibm'],
  });
});

scenario('exchange.headers_typed_values', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const qAll = await tempQueue(ch);
  const qAny = await tempQueue(ch);
  await ch.bindQueue(qAll, 'amq.headers', '', { 'x-match': 'all', n: 5, flag: true });
  await ch.bindQueue(qAny, 'amq.headers', '', { 'x-match': 'any', n: 5, s: 'v' });
  const pubs = [['1', { n: 5, flag: true }], ['2', { n: 5 }], ['3', { s: 'v' }], ['4', { n: 6, flag: true }], ['5', { n: '5', flag: true }]];
  for (const [b, h] of pubs) ch.publish('amq.headers', '', Buffer.from(b), { headers: h });
  await ch.waitForConfirms();
  t.eq('all', await getAll(ch, qAll), ['1']);
  t.eq('any', await getAll(ch, qAny), ['1', '2', '3']);
});

scenario('exchange.e2e_fanout_to_direct', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const src = t.n('js-src');
  const dst = t.n('js-dst');
  t.defer(async () => { await ch.deleteExchange(src); await ch.deleteExchange(dst); });
  await ch.assertExchange(src, 'fanout', { durable: false });
  await ch.assertExchange(dst, 'direct', { durable: false });
  await ch.bindExchange(dst, src, 'ignored');
  const q = await tempQueue(ch);
  await ch.bindQueue(q, dst, 'k1');
  ch.publish(src, 'k1', Buffer.from('a'));
  ch.publish(src, 'k2', Buffer.from('b'));
  await ch.waitForConfirms();
  t.eq('fanout source copies with the original key; direct filters on it', await getAll(ch, q), ['a']);
  await ch.bindExchange(dst, src, 'k1');
  await ch.unbindExchange(dst, src, 'ignored');
  t.eq('bindings changed', true, true);
  const d2 = t.n('js-dst2');
  t.defer(() => ch.deleteExchange(d2));
  await ch.assertExchange(d2, 'fanout', { durable: false });
  await ch.bindExchange(d2, src, '');
  const q2 = await tempQueue(ch);
  await ch.bindQueue(q2, d2, '');
  ch.publish(src, 'anything', Buffer.from('c'));
  await ch.waitForConfirms();
  t.eq('fanout to fanout', await getAll(ch, q2), ['c']);
});

scenario('exchange.delete_missing_and_passive', async (t) => {
  const c = await connect(t);
  let ch = await chan(c);
  await ch.deleteExchange(t.n('nope'));
  t.obs('delete missing ok', true);
  await channelError(t, 'checkExchange missing', () => ch.checkExchange(t.n('nope')), 404);
  ch = await chan(c);
  await channelError(t, 'declare amq.x', () => ch.assertExchange('amq.' + t.n('x'), 'direct'), 403);
});

// queues ----------------------------------------------------------------------

scenario('queue.assert_options_roundtrip', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const name = t.n('js-opts');
  t.defer(() => ch.deleteQueue(name));
  const opts = { durable: false, messageTtl: 60000, expires: 600000, maxLength: 100, deadLetterExchange: 'amq.fanout', deadLetterRoutingKey: 'dl', maxPriority: 3 };
  const ok = await ch.assertQueue(name, opts);
  t.eq('declare-ok', [ok.messageCount, ok.consumerCount], [0, 0]);
  const ok2 = await ch.assertQueue(name, opts);
  t.eq('same args redeclare', ok2.messageCount, 0);
  await channelError(t, 'different max-length', () => ch.assertQueue(name, { ...opts, maxLength: 5 }), 406);
});

scenario('queue.dead_letter_via_nack', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const dlq = await tempQueue(ch);
  const q = await tempQueue(ch, { deadLetterExchange: '', deadLetterRoutingKey: dlq });
  ch.sendToQueue(q, Buffer.from('poison'), { headers: { attempt: 1 } });
  await ch.waitForConfirms();
  const m = await ch.get(q);
  ch.nack(m, false, false);
  await waitUntil(async () => (await ch.checkQueue(dlq)).messageCount === 1, HANG_MS, 'dead letter');
  const d = await ch.get(dlq, { noAck: true });
  const xd = d.properties.headers['x-death'][0];
  t.eq('dead letter', [d.content.toString(), d.fields.exchange, d.fields.routingKey, d.properties.headers.attempt], ['poison', '', dlq, 1]);
  t.eq('x-death', [xd.reason, xd.queue, xd.count, xd.exchange, xd['routing-keys']], ['rejected', q, 1, '', [q]]);
});

scenario('queue.priority_consumer_order', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch, { maxPriority: 10 });
  [[1, 'low'], [10, 'top'], [5, 'mid'], [0, 'zero'], [5, 'mid2']].forEach(([p, b]) => ch.sendToQueue(q, Buffer.from(b), { priority: p }));
  await ch.waitForConfirms();
  const col = collector(5);
  await ch.consume(q, (m) => col.push(m.content.toString()), { noAck: true });
  t.eq('priority order', await within(col.done, HANG_MS, 'deliveries'), ['top', 'mid', 'mid2', 'low', 'zero']);
});

scenario('queue.exclusive_other_connection', async (t) => {
  const c1 = await connect(t);
  const c2 = await connect(t);
  const ch1 = await chan(c1);
  const q = t.n('js-excl');
  await ch1.assertQueue(q, { exclusive: true });
  const ch2 = await chan(c2);
  await channelError(t, 'assert from other connection', () => ch2.assertQueue(q, { exclusive: true }), 405);
});

scenario('queue.delete_if_empty', async (t) => {
  const c = await connect(t);
  let ch = await chan(c, true);
  const q = t.n('js-ifempty');
  t.defer(async () => { const c2 = await amqp.connect(t.url); const x = await c2.createChannel(); await x.deleteQueue(q); await c2.close(); });
  await ch.assertQueue(q);
  ch.sendToQueue(q, Buffer.from('x'));
  await ch.waitForConfirms();
  await channelError(t, 'delete if_empty', () => ch.deleteQueue(q, { ifEmpty: true }), 406);
  ch = await chan(c);
  const ok = await ch.deleteQueue(q);
  t.eq('delete count', ok.messageCount, 1);
});

scenario('queue.ttl_and_expiration', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch, { messageTtl: 100 });
  ch.sendToQueue(q, Buffer.from('queue-ttl'));
  const q2 = await tempQueue(ch);
  ch.sendToQueue(q2, Buffer.from('msg-exp'), { expiration: 100 });
  ch.sendToQueue(q2, Buffer.from('keep'));
  await ch.waitForConfirms();
  await sleep(400);
  t.eq('queue ttl', await getAll(ch, q), []);
  t.eq('message expiration', await getAll(ch, q2), ['keep']);
});

// consumers and acks --------------------------------------------------------------

scenario('consume.prefetch_fair_dispatch', async (t) => {
  const c = await connect(t);
  const pub = await chan(c, true);
  const q = await tempQueue(pub);
  const slow = await chan(c);
  const fast = await chan(c);
  await slow.prefetch(1);
  await fast.prefetch(1);
  const got = { slow: [], fast: [] };
  let slowMsg = null;
  await slow.consume(q, (m) => { got.slow.push(m.content.toString()); slowMsg = m; });
  await fast.consume(q, (m) => { got.fast.push(m.content.toString()); fast.ack(m); });
  for (let i = 0; i < 10; i++) pub.sendToQueue(q, Buffer.from(String(i)));
  await pub.waitForConfirms();
  await waitUntil(() => got.fast.length + got.slow.length === 10 || (got.fast.length === 9 && got.slow.length === 1), HANG_MS, 'dispatch');
  t.eq('slow consumer holds only one', got.slow.length, 1);
  t.eq('fast consumer took the rest', got.fast.length, 9);
  slow.ack(slowMsg);
});

scenario('consume.server_cancel_callback', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = t.n('js-cancel');
  await ch.assertQueue(q);
  let cancelled = false;
  const ok = await ch.consume(q, (m) => { if (m === null) cancelled = true; });
  const other = await chan(c);
  await other.deleteQueue(q);
  await waitUntil(() => cancelled, HANG_MS, 'consumer cancel');
  t.eq('consumer got null (basic.cancel)', cancelled, true);
  t.obs('tag', ok.consumerTag);
});

scenario('consume.consumer_priority', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  const got = [];
  await ch.consume(q, (m) => got.push('low'), { noAck: true, priority: 1 });
  await ch.consume(q, (m) => got.push('high'), { noAck: true, priority: 10 });
  for (let i = 0; i < 5; i++) ch.sendToQueue(q, Buffer.from('x'));
  await ch.waitForConfirms();
  await waitUntil(() => got.length === 5, HANG_MS, 'deliveries');
  t.eq('higher priority consumer gets everything', got, ['high', 'high', 'high', 'high', 'high']);
});

scenario('consume.exclusive_and_tags', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = await tempQueue(ch);
  const ok = await ch.consume(q, () => {}, { consumerTag: 'js-tag', exclusive: true });
  t.eq('consumer tag echoed', ok.consumerTag, 'js-tag');
  await ch.cancel('js-tag');
  const gen = await ch.consume(q, () => {}, { consumerTag: '' });
  t.check(/^amq\.ctag-/.test(gen.consumerTag), `generated tag ${gen.consumerTag}`);
  t.obs('generated', gen.consumerTag);
  const ch2 = await chan(c);
  await ch2.consume(q, () => {});
  await channelError(t, 'exclusive while others consume', () => ch.consume(q, () => {}, { exclusive: true }), 403);
});

scenario('ack.nack_all_and_ack_all', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = await tempQueue(ch);
  for (let i = 0; i < 4; i++) ch.sendToQueue(q, Buffer.from(String(i)));
  await waitUntil(async () => (await ch.checkQueue(q)).messageCount === 4);
  for (let i = 0; i < 4; i++) await ch.get(q);
  ch.nackAll(true);
  const again = [];
  for (let i = 0; i < 4; i++) {
    const m = await ch.get(q);
    again.push([m.content.toString(), m.fields.redelivered, m.fields.deliveryTag]);
  }
  t.eq('requeued in order, redelivered', again, [['0', true, 5], ['1', true, 6], ['2', true, 7], ['3', true, 8]]);
  ch.ackAll();
  t.eq('empty after ackAll', (await ch.checkQueue(q)).messageCount, 0);
});

scenario('ack.recover', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = await tempQueue(ch);
  const got = [];
  await ch.consume(q, (m) => got.push([m.content.toString(), m.fields.redelivered]));
  ch.sendToQueue(q, Buffer.from('r'));
  await waitUntil(() => got.length === 1);
  await ch.recover();
  await waitUntil(() => got.length === 2, HANG_MS, 'redelivery');
  t.eq('redelivered after recover', got, [['r', false], ['r', true]]);
  ch.ackAll();
});

scenario('ack.reject_unknown_tag', async (t) => {
  const c = await connect(t);
  const ch = await chan(c);
  const q = await tempQueue(ch);
  const closed = closedWith(ch);
  ch.ack({ fields: { deliveryTag: 99 } });
  const e = await within(closed, HANG_MS, 'channel close');
  t.eq('ack unknown tag', errInfo(e), [406, 'PRECONDITION_FAILED']);
});

scenario('get.message_count', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  t.eq('empty', await ch.get(q), false);
  for (let i = 0; i < 3; i++) ch.sendToQueue(q, Buffer.from(`m${i}`));
  await ch.waitForConfirms();
  const m = await ch.get(q, { noAck: true });
  t.eq('get-ok', [m.content.toString(), m.fields.messageCount, m.fields.deliveryTag, m.fields.redelivered, m.fields.routingKey], ['m0', 2, 1, false, q]);
});

// publishing ------------------------------------------------------------------------

scenario('confirm.many_with_callbacks', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  let acked = 0;
  for (let i = 0; i < 1000; i++) {
    ch.sendToQueue(q, Buffer.from(String(i)), {}, (err) => { if (!err) acked++; });
  }
  await ch.waitForConfirms();
  t.eq('acked', acked, 1000);
  t.eq('queued', (await ch.checkQueue(q)).messageCount, 1000);
});

scenario('confirm.publish_to_missing_exchange', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const closed = closedWith(ch);
  ch.publish(t.n('nope'), 'k', Buffer.from('x'));
  const e = await within(closed, HANG_MS, 'channel close');
  t.eq('channel closed', errInfo(e), [404, 'NOT_FOUND']);
});

scenario('mandatory.return_event', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const returned = [];
  ch.on('return', (m) => returned.push([m.fields.replyCode, m.fields.replyText, m.fields.exchange, m.fields.routingKey, m.content.toString(), m.properties.correlationId]));
  ch.publish('amq.direct', t.n('no-binding'), Buffer.from('back'), { mandatory: true, correlationId: 'c-1' });
  await ch.waitForConfirms();
  await waitUntil(() => returned.length === 1);
  t.eq('returned', returned, [[312, 'NO_ROUTE', 'amq.direct', t.n('no-binding'), 'back', 'c-1']]);
});

scenario('body.large_5mib_and_empty', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  const big = Buffer.alloc(5 * 1024 * 1024);
  for (let i = 0; i < big.length; i++) big[i] = (i * 31) % 256;
  ch.sendToQueue(q, big);
  ch.sendToQueue(q, Buffer.alloc(0));
  await ch.waitForConfirms();
  const col = collector(2);
  await ch.consume(q, (m) => col.push(m), { noAck: true });
  const [a, b] = await within(col.done, 30000, 'large message');
  t.eq('large intact', [a.content.length, a.content.equals(big)], [big.length, true]);
  t.eq('empty', b.content.length, 0);
});

scenario('properties.all_fields', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  const props = {
    contentType: 'application/json', contentEncoding: 'utf-8', headers: { k: 'v' }, deliveryMode: 2, priority: 3,
    correlationId: 'cid', replyTo: 'rq', expiration: '100000', messageId: 'mid', timestamp: 1700000000, type: 't', userId: t.user, appId: 'js',
  };
  ch.sendToQueue(q, Buffer.from('p'), props);
  await ch.waitForConfirms();
  const m = await ch.get(q, { noAck: true });
  const p = {};
  for (const k of Object.keys(props)) p[k] = m.properties[k];
  t.eq('properties', p, props);
});

scenario('properties.header_types', async (t) => {
  const c = await connect(t);
  const ch = await chan(c, true);
  const q = await tempQueue(ch);
  const headers = {
    s: 'str', i: 42, neg: -7, big: 2 ** 40, dbl: 2.5, f: { '!': 'float', value: 0.5 }, b: true,
    ts: { '!': 'timestamp', value: 1700000000 }, dec: { '!': 'decimal', value: { places: 2, digits: 314 } },
    tbl: { inner: { x: 1 } }, arr: [1, 'a', false, [2]], buf: Buffer.from([0, 1, 2]), nul: null,
    i8: { '!': 'byte', value: -3 }, i16: { '!': 'int16', value: 300 }, u8: { '!': 'unsignedbyte', value: 250 },
  };
  ch.sendToQueue(q, Buffer.from('h'), { headers });
  await ch.waitForConfirms();
  const m = await ch.get(q, { noAck: true });
  t.eq('decoded headers', m.properties.headers, {
    s: 'str', i: 42, neg: -7, big: 2 ** 40, dbl: 2.5, f: 0.5, b: true, ts: { '!': 'timestamp', value: 1700000000 }, dec: { '!': 'decimal', value: { places: 2, digits: 314 } },
    tbl: { inner: { x: 1 } }, arr: [1, 'a', false, [2]], buf: Buffer.from([0, 1, 2]), nul: null, i8: -3, i16: 300, u8: 250,
  });
});

// realistic loads -------------------------------------------------------------------

scenario('load.rpc', async (t) => {
  const server = await connect(t);
  const client = await connect(t);
  const sch = await chan(server);
  const rq = await tempQueue(sch);
  await sch.prefetch(10);
  await sch.consume(rq, (m) => {
    const n = Number(m.content.toString());
    sch.sendToQueue(m.properties.replyTo, Buffer.from(String(n + 1000)), { correlationId: m.properties.correlationId });
    sch.ack(m);
  });
  const cch = await chan(client);
  const reply = await tempQueue(cch);
  const answers = new Map();
  await cch.consume(reply, (m) => answers.set(m.properties.correlationId, Number(m.content.toString())), { noAck: true });
  for (let i = 0; i < 100; i++) cch.sendToQueue(rq, Buffer.from(String(i)), { replyTo: reply, correlationId: `id-${i}` });
  await waitUntil(() => answers.size === 100, 15000, 'rpc answers');
  let right = 0;
  for (let i = 0; i < 100; i++) if (answers.get(`id-${i}`) === i + 1000) right++;
  t.eq('correct answers', right, 100);
});

scenario('load.work_queue_three_workers', async (t) => {
  const c = await connect(t);
  const pub = await chan(c, true);
  const q = t.n('js-work');
  t.defer(() => pub.deleteQueue(q));
  await pub.assertQueue(q, { durable: true });
  const seen = [];
  const perWorker = [0, 0, 0];
  for (let w = 0; w < 3; w++) {
    const wc = await connect(t);
    const ch = await chan(wc);
    await ch.prefetch(5);
    await ch.consume(q, (m) => {
      seen.push(Number(m.content.toString()));
      perWorker[w]++;
      setTimeout(() => ch.ack(m), 1);
    });
  }
  for (let i = 0; i < 900; i++) pub.sendToQueue(q, Buffer.from(String(i)), { persistent: true });
  await pub.waitForConfirms();
  await waitUntil(() => seen.length >= 900, 20000, 'all work');
  await sleep(100);
  t.eq('each job once', [...seen].sort((a, b) => a - b).join(',') === [...Array(900).keys()].join(','), true);
  t.check(perWorker.every((n) => n > 0), `every worker got work: ${perWorker}`);
});
