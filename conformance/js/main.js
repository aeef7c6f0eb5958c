'use strict';
// JavaScript scenario driver (amqplib). See harness.js for the protocol.
require('./scenarios');
require('./harness').main().then(() => process.exit(0), (e) => { console.error(e); process.exit(1); });
