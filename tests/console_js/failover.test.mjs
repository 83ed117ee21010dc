// Moving to another gateway's console: the list taken from the page's URL, the next gateway
// chosen, and a round that ends instead of passing the page round dead gateways.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import {
  Failover,
  MAX_GATEWAYS,
  candidates,
  consoleAddress,
  failoverState,
  moveUrl,
  parseGateways,
  withRoundEnded,
} from '../../gateway/console/js/failover.js';

const A = 'http://127.0.0.1:8080/';
const B = 'http://127.0.0.1:8081/';
const C = 'http://127.0.0.1:8082/';

test('only absolute http and https console URLs are taken into the list', () => {
  const { gateways, rejected } = parseGateways(
    ` ${B}?x=1#scout1 ,javascript:alert(1),data:text/html,hi,/relative,https://gw.example/console/index.html,http://u:p@gw.example/,${B}`,
  );
  assert.deepEqual(gateways, [B, 'https://gw.example/console/']);
  assert.equal(rejected.length, 5, rejected.join(' | '));
  assert.match(rejected[0], /only http and https consoles are taken, not javascript:/);
  assert.match(rejected.join(' '), /carries no credentials/);
  assert.throws(() => consoleAddress('vbscript:x'), /not vbscript:/);
});

test('a list longer than the bound keeps its first gateways and says what it left', () => {
  const many = Array.from({ length: MAX_GATEWAYS + 2 }, (_, i) => `http://10.0.0.${i + 1}:8080/`);
  const { gateways, rejected } = parseGateways(many.join(','));
  assert.equal(gateways.length, MAX_GATEWAYS);
  assert.equal(rejected.length, 2);
  assert.match(rejected[0], /more than 16 gateways/);
});

test('the round holds the page own gateway and the next one follows it, wrapping round', () => {
  const state = failoverState(`${B}?gateways=${A},${B},${C}#scout1`);
  assert.deepEqual(state.round, [A, B, C]);
  assert.deepEqual(candidates(state), [C, A]);
  const unlisted = failoverState(`${A}?gateways=${B},${C}`);
  assert.deepEqual(unlisted.round, [A, B, C]);
  assert.deepEqual(candidates(unlisted), [B, C]);
  assert.deepEqual(candidates(failoverState(A)), [], 'no list: nowhere to go');
});

test('a move carries the list, the service and where the page came from', () => {
  const state = failoverState(`${A}?gateways=${B},${C}#scout1`);
  const url = new URL(moveUrl(B, state, '#scout1'));
  assert.equal(url.origin + url.pathname, B);
  assert.equal(url.hash, '#scout1');
  const arrived = failoverState(url.href);
  assert.deepEqual(arrived.round, [A, B, C]);
  assert.equal(arrived.from, A);
  assert.deepEqual(candidates(arrived), [C], 'the gateway it left is not gone back to in this round');
  const last = failoverState(moveUrl(C, arrived, '#scout1'));
  assert.deepEqual(last.tried, [A, B]);
  assert.deepEqual(candidates(last), [], 'every gateway tried: the round is over');
  assert.equal(new URL(withRoundEnded(url.href)).searchParams.get('tried'), null);
  assert.equal(new URL(withRoundEnded(url.href)).searchParams.get('gateways'), [A, B, C].join(','));
});

/** Timers the test fires by hand. */
function manualTimers() {
  const pending = new Map();
  let next = 1;
  return {
    pending,
    setTimeout(fn, ms) {
      pending.set(next, { fn, ms });
      return next++;
    },
    clearTimeout(id) {
      pending.delete(id);
    },
    async fire() {
      const [[id, { fn }]] = pending;
      pending.delete(id);
      await fn();
    },
  };
}

function watcher(href, answering) {
  const timers = manualTimers();
  const seen = { probes: [], moves: [], notices: [], ended: 0 };
  const failover = new Failover({
    href,
    hash: () => '#scout1',
    probe: async (address) => {
      seen.probes.push(address);
      return answering.includes(address);
    },
    move: (url) => seen.moves.push(url),
    notice: (text) => seen.notices.push(text),
    endRound: () => (seen.ended += 1),
    afterMs: 10000,
    timers,
  });
  return { failover, timers, seen };
}

test('a gateway unreachable past the bound sends the page to the next one that answers', async () => {
  const { failover, timers, seen } = watcher(`${A}?gateways=${B},${C}`, [C]);
  failover.stateChanged('connecting');
  failover.stateChanged('closed');
  assert.equal(timers.pending.size, 1, 'one wait, however many state changes');
  assert.equal([...timers.pending.values()][0].ms, 10000);
  await timers.fire();
  assert.deepEqual(seen.probes, [B, C], 'the silent one is skipped');
  assert.equal(seen.moves.length, 1);
  const url = new URL(seen.moves[0]);
  assert.equal(url.origin + url.pathname, C);
  assert.equal(url.hash, '#scout1');
  assert.equal(url.searchParams.get('tried'), A);
});

test('a stream that opens again within the bound keeps the page where it is', async () => {
  const { failover, timers, seen } = watcher(`${A}?gateways=${B}`, [B]);
  failover.stateChanged('closed');
  failover.stateChanged('open');
  assert.equal(timers.pending.size, 0);
  assert.deepEqual(seen.moves, []);
});

test('after a full round the page stays and names every address tried', async () => {
  const { failover, timers, seen } = watcher(`${B}?gateways=${A},${B},${C}&tried=${A}`, [A]);
  assert.deepEqual(seen.notices, [`moved here from ${A} (unreachable)`]);
  failover.stateChanged('closed');
  await timers.fire();
  assert.deepEqual(seen.probes, [C], 'the gateway it came from is not probed again in this round');
  assert.deepEqual(seen.moves, []);
  assert.equal(seen.notices.at(-1), `every gateway unreachable (tried ${B}, ${A}, ${C}); staying here`);
  failover.stateChanged('open');
  assert.equal(seen.notices.at(-1), '', 'back live: the notice goes');
  assert.equal(seen.ended, 1, 'an open stream ends the round');
  failover.stateChanged('closed');
  await timers.fire();
  assert.equal(seen.moves.length, 1, 'a new round may go back to the gateway it once left');
});

test('a page without a list never looks elsewhere', () => {
  const { failover, timers } = watcher(A, []);
  failover.stateChanged('closed');
  assert.equal(failover.enabled, false);
  assert.equal(timers.pending.size, 0);
});
