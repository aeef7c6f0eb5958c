'use strict';
// JavaScript scenario driver (amqplib). See harness.js for the protocol.
// `--semantics`: the semantics suite's scenarios (semantics.js) instead.
require(process.argv.includes('--semantics') ? './semantics' : './scenarios');
require('./harness').main().then(() => process.exit(0), (e) => { console.error(e); process.exit(1); });
