// MQTT <-> AMQP checks with mqtt.js (issue 32) and amqplib, through one broker:
//   node mqtt-amqp.js --amqp-port P --mqtt-port M [--v5]
// One JSON line per check, {"name", "outcome"}, as python/mqtt_amqp.py:
// MQTT 3.1.1 checks (compared with RabbitMQ 3.10's rabbitmq_mqtt by
// lib/mqtt_amqp.py), and with --v5 MQTT 5.0 user properties and content type
// both ways (Leveret only: RabbitMQ 3.10 has no MQTT 5.0).
'use strict';
const mqtt = require('mqtt');
const amqp = require('amqplib');
const crypto = require('crypto');

const RUN = crypto.randomBytes(3).toString('hex');
const args = process.argv.slice(2);
const arg = (name) => { const i = args.indexOf(name); return i >= 0 ? args[i + 1] : undefined; };
const AMQP_PORT = Number(arg('--amqp-port'));
const MQTT_PORT = Number(arg('--mqtt-port'));
const V5 = args.includes('--v5');
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function connectMqtt(protocolVersion) {
  return mqtt.connectAsync(`mqtt://127.0.0.1:${MQTT_PORT}`, {
    username: 'guest', password: 'guest', protocolVersion, clientId: `mqttjs-${crypto.randomBytes(4).toString('hex')}`,
    reconnectPeriod: 0, connectTimeout: 10000,
  });
}

async function withAmqp(fn) {
  const conn = await amqp.connect(`amqp://guest:guest@127.0.0.1:${AMQP_PORT}`);
  try {
    const ch = await conn.createChannel();
    return await fn(ch);
  } finally {
    await conn.close();
  }
}

async function boundQueue(ch, key) {
  const { queue } = await ch.assertQueue('', { exclusive: true });
  await ch.bindQueue(queue, 'amq.topic', key);
  return queue;
}

async function drain(ch, queue, want, ms = 10000) {
  const got = [];
  const deadline = Date.now() + ms;
  while (got.length < want && Date.now() < deadline) {
    const m = await ch.get(queue, { noAck: true });
    if (!m) { await sleep(50); continue; }
    const headers = {};
    for (const k of Object.keys(m.properties.headers || {}).sort()) headers[k] = String(m.properties.headers[k]);
    got.push({
      exchange: m.fields.exchange, routing_key: m.fields.routingKey, delivery_mode: m.properties.deliveryMode ?? null,
      headers, content_type: m.properties.contentType ?? null, body: m.content.toString(),
    });
  }
  return got;
}

async function mqttToAmqp() {
  return withAmqp(async (ch) => {
    const q = await boundQueue(ch, `j.${RUN}.*`);
    const c = await connectMqtt(4);
    for (const qos of [0, 1]) await c.publishAsync(`j/${RUN}/q${qos}`, `mqtt.js qos ${qos}`, { qos });
    const got = await drain(ch, q, 2);
    await c.endAsync();
    return got.sort((a, b) => a.body.localeCompare(b.body));
  });
}

async function amqpToMqtt() {
  const got = { 0: [], 1: [] };
  const subs = [];
  for (const qos of [0, 1]) {
    const c = await connectMqtt(4);
    c.on('message', (topic, payload, packet) => got[qos].push([topic, payload.toString(), packet.qos, !!packet.retain]));
    await c.subscribeAsync(`k/${RUN}/+`, { qos });
    subs.push(c);
  }
  await withAmqp(async (ch) => {
    for (const mode of [1, 2]) {
      ch.publish('amq.topic', `k.${RUN}.m${mode}`, Buffer.from(`delivery mode ${mode}`),
        { deliveryMode: mode, contentType: 'text/plain', headers: { h: 'v' } });
    }
    const deadline = Date.now() + 10000;
    while (Date.now() < deadline && (got[0].length < 2 || got[1].length < 2)) await sleep(50);
    await sleep(300);
  });
  for (const c of subs) await c.endAsync();
  return { 'subscriber qos 0': got[0].sort(), 'subscriber qos 1': got[1].sort() };
}

async function v5Properties() {
  return withAmqp(async (ch) => {
    const q = await boundQueue(ch, `j5.${RUN}.in`);
    const c = await connectMqtt(5);
    await c.publishAsync(`j5/${RUN}/in`, 'v5', {
      qos: 1, properties: { contentType: 'text/csv', userProperties: { sensor: 'lidar', unit: 'm' } },
    });
    const inbound = await drain(ch, q, 1);
    const outbound = [];
    c.on('message', (topic, payload, packet) => {
      const p = packet.properties || {};
      outbound.push({ topic, payload: payload.toString(), content_type: p.contentType ?? null,
        user_properties: p.userProperties ?? null });
    });
    await c.subscribeAsync(`j5/${RUN}/out`, { qos: 1 });
    ch.publish('amq.topic', `j5.${RUN}.out`, Buffer.from('out'),
      { deliveryMode: 2, contentType: 'application/cbor', headers: { robot: 'r7' } });
    const deadline = Date.now() + 10000;
    while (!outbound.length && Date.now() < deadline) await sleep(50);
    await c.endAsync();
    return { 'mqtt to amqp': inbound, 'amqp to mqtt': outbound };
  });
}

const CHECKS = [
  ['mqtt.js 3.1.1 -> amqplib: QoS 0 and 1 publishes as AMQP messages', mqttToAmqp],
  ['amqplib -> mqtt.js 3.1.1: delivery modes to QoS 0 and 1 subscribers', amqpToMqtt],
];
if (V5) CHECKS.push(['mqtt.js 5.0 <-> amqplib: content type and user properties', v5Properties]);

(async () => {
  for (const [name, check] of CHECKS) {
    let outcome;
    try {
      outcome = await check();
    } catch (e) {
      outcome = `error: ${e && e.message}`;
    }
    console.log(JSON.stringify({ name, outcome }).split(RUN).join('<run>'));
  }
  process.exit(0);
})();
