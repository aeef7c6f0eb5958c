'use strict';
// The TLS suite's checks with amqplib: node tls.js --certs DIR --port PORT
// One JSON line per check: {"name", "outcome"}, outcome "ok" or "refused: ...".
const fs = require('fs');
const path = require('path');
const amqp = require('amqplib');

function arg(name) {
  const i = process.argv.indexOf(name);
  if (i < 0) throw new Error(`missing ${name}`);
  return process.argv[i + 1];
}

async function check(port, dir, { ca, client, external }) {
  const options = { ca: [fs.readFileSync(path.join(dir, ca))], servername: 'localhost', timeout: 20000 };
  if (client) {
    options.cert = fs.readFileSync(path.join(dir, `${client}.pem`));
    options.key = fs.readFileSync(path.join(dir, `${client}.key`));
  }
  if (external) options.credentials = amqp.credentials.external();
  const url = external ? `amqps://localhost:${port}` : `amqps://guest:guest@localhost:${port}`;
  let connection;
  try {
    connection = await amqp.connect(url, options);
    connection.on('error', () => {});
    const ch = await connection.createChannel();
    const { queue } = await ch.assertQueue('', { exclusive: true });
    ch.sendToQueue(queue, Buffer.from('tls'));
    await ch.prefetch(1);
    const got = await ch.get(queue, { noAck: true });
    await connection.close();
    return got && got.content.toString() === 'tls' ? 'ok' : 'refused: the message did not come back';
  } catch (e) {
    if (connection) await connection.close().catch(() => {});
    return `refused: ${e && e.message}`;
  }
}

async function main() {
  const dir = arg('--certs');
  const port = arg('--port');
  const checks = [
    ['handshake, PLAIN, round trip', { ca: 'ca.pem' }],
    ['mutual TLS, EXTERNAL as robot-7', { ca: 'ca.pem', client: 'client', external: true }],
    ['server not trusted (rogue CA)', { ca: 'rogue-ca.pem' }],
    ['client certificate from a rogue CA', { ca: 'ca.pem', client: 'rogue', external: true }],
  ];
  for (const [name, spec] of checks) {
    console.log(JSON.stringify({ name, outcome: await check(port, dir, spec) }));
  }
}

main().then(() => process.exit(0), (e) => { console.error(e); process.exit(1); });
