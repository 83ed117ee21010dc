// The value grammar as the console reads and writes it: the same texts as services/kernel/values.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import {
  ValueFormatError,
  findMarkers,
  formatList,
  formatMarker,
  formatNumber,
  formatVector,
  markerAt,
  markerFromInput,
  markerLocation,
  parseBool,
  parseList,
  parseMarker,
  parseNames,
  parseNumber,
  parseVector,
  valueFromInput,
} from '../../gateway/console/js/values.js';

test('numbers parse strictly and format as the services format them', () => {
  assert.equal(parseNumber(' 0.5 '), 0.5);
  assert.equal(parseNumber('-3e-2'), -0.03);
  assert.equal(formatNumber(2), '2');
  assert.equal(formatNumber(-0), '0');
  assert.equal(formatNumber(0.1 + 0.2), '0.30000000000000004'); // exact, as Python's repr
  for (const bad of ['', 'nan', 'inf', '1,5', '0x10', '1e999']) {
    assert.throws(() => parseNumber(bad), ValueFormatError, bad);
  }
  assert.throws(() => formatNumber(Number.NaN), /only finite numbers/);
  assert.match(errorOf(() => parseNumber('1,5')), /use a dot as the decimal point/);
});

test('booleans accept the words the grammar accepts', () => {
  for (const t of ['true', 'TRUE', '1', 'on', 'yes']) assert.equal(parseBool(t), true);
  for (const f of ['false', '0', 'off', 'No']) assert.equal(parseBool(f), false);
  assert.throws(() => parseBool('maybe'), /also accepted: 1\/0/);
});

test('vectors round-trip and bad ones say why', () => {
  assert.deepEqual(parseVector('(1 2.5 -3e-2)'), [1, 2.5, -0.03]);
  assert.deepEqual(parseVector(' () '), []);
  assert.equal(formatVector([1, 2.5, -0.03]), '(1 2.5 -0.03)');
  assert.equal(formatVector(parseVector('(0 0 0 0 0 1.5707963267948966)')), '(0 0 0 0 0 1.5707963267948966)');
  assert.match(errorOf(() => parseVector('1 2')), /enclosed in parentheses/);
  assert.match(errorOf(() => parseVector('(1, 2)')), /not commas/);
  assert.match(errorOf(() => parseVector('(1 (2))')), /not nested lists/);
  assert.match(errorOf(() => parseVector('(1 2) x')), /text after the closing/);
  assert.match(errorOf(() => parseVector('(1 2')), /unclosed/);
  assert.match(errorOf(() => parseVector('x'.repeat(70000))), /the limit is 65536/);
});

test('lists and names are s-expressions of words', () => {
  assert.deepEqual(parseList('((1 2) (a b (c 1)))'), [['1', '2'], ['a', 'b', ['c', '1']]]);
  assert.equal(formatList([[1, 2], ['a', true]]), '((1 2) (a true))');
  assert.deepEqual(parseNames('(location velocity behaviors.moveto)'), ['location', 'velocity', 'behaviors.moveto']);
  assert.match(errorOf(() => parseList('(a))')), /after the end of the list|unmatched/);
  assert.match(errorOf(() => parseList('((a)')), /1 unclosed/);
  assert.match(errorOf(() => parseNames('(a (b))')), /nested list/);
  assert.match(errorOf(() => parseList('('.repeat(40) + ')'.repeat(40))), /deeper than 32/);
  assert.throws(() => formatList(['two words']), /words without spaces/);
});

test('markers parse to fields and format back to the same text', () => {
  const text = '<marker><location>(1 2)</location><name>box &amp; lid</name><pose><yaw>0.5</yaw></pose></marker>';
  const marker = parseMarker(text);
  assert.equal(marker.tag, 'marker');
  assert.equal(marker.fields.location, '(1 2)');
  assert.equal(marker.fields.name, 'box & lid');
  assert.deepEqual(marker.fields.pose, { tag: 'pose', fields: { yaw: '0.5' } });
  assert.equal(formatMarker(marker), text);
  assert.deepEqual(markerLocation(marker), [1, 2]);
  assert.equal(markerAt([3, -1.5]), '<marker><location>(3 -1.5)</location></marker>');
  assert.deepEqual(parseMarker('<marker></marker>'), { tag: 'marker', fields: {} });
  assert.deepEqual(parseMarker('<marker><seen/></marker>'), { tag: 'marker', fields: { seen: '' } });
});

test('markers refuse what the services refuse', () => {
  assert.match(errorOf(() => parseMarker('<marker a="1"><x>1</x></marker>')), /attributes/);
  assert.match(errorOf(() => parseMarker('<!DOCTYPE x><marker></marker>')), /not an XML element|declarations/);
  assert.match(errorOf(() => parseMarker('<marker>text<x>1</x></marker>')), /mixes text/);
  assert.match(errorOf(() => parseMarker('<marker><x>1</x><x>2</x></marker>')), /more than one <x>/);
  assert.match(errorOf(() => parseMarker('<marker><x>1</y></marker>')), /closed by another tag/);
  assert.match(errorOf(() => parseMarker('<marker><x>&bogus;</x></marker>')), /unknown entity/);
  assert.match(errorOf(() => parseMarker('<marker><location>(1 2)</location></marker> more')), /after the root/);
  assert.throws(() => formatMarker({ tag: 'marker', fields: { 'bad name': '1' } }), /bad marker field name/);
});

test('every marker of a list is found, and a broken one is skipped', () => {
  const text =
    '(<marker><location>(1 2)</location></marker> <marker><location>(3 4)</location><color>(1 0 0)</color></marker>' +
    ' <marker><location>(5 6)</oops></marker>)';
  const found = findMarkers(text);
  assert.equal(found.length, 2);
  assert.deepEqual(found.map(markerLocation), [[1, 2], [3, 4]]);
  assert.equal(found[1].fields.color, '(1 0 0)');
  assert.equal(findMarkers(text, 1).length, 1);
  assert.deepEqual(findMarkers(42), []);
});

test('form input becomes value text by the property type', () => {
  assert.equal(valueFromInput('number', ' 1.50 '), '1.5');
  assert.equal(valueFromInput('integer', '42'), '42');
  assert.throws(() => valueFromInput('integer', '4.2'), /has a fraction/);
  assert.equal(valueFromInput('boolean', 'on'), 'true');
  assert.equal(valueFromInput('vector', '1 2 3'), '(1 2 3)');
  assert.equal(valueFromInput('vector', '(1  2)'), '(1 2)');
  assert.equal(valueFromInput('text', ' as typed '), ' as typed ');
  assert.equal(markerFromInput('2 3'), '<marker><location>(2 3)</location></marker>');
  assert.equal(markerFromInput('(2 3)'), '<marker><location>(2 3)</location></marker>');
  assert.equal(markerFromInput('<marker></marker>'), '<marker></marker>');
  assert.throws(() => markerFromInput('here'), ValueFormatError);
});

function errorOf(f) {
  try {
    f();
  } catch (e) {
    return e.message;
  }
  throw new Error('expected an error');
}
