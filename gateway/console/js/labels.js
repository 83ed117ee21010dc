// Where the map's names go: each beside its thing, clear of every other name and of every other
// thing's shape, so that the names of things standing together stay readable ("thermo1" and
// "swarm" side by side, never "thermo1arm"). Pure: boxes in, places out (screen pixels, y down),
// so that it runs the same in node's tests and in the page.
//
// Each name tries the eight places around its thing (its kind's favourite first), then the same
// places further out, RING_STEP_PX a ring; a name set off its thing past the first ring gets a
// leader line back to it. When every place is taken the one overlapping least is used. Placed
// boxes are filed in a grid of CELL_PX squares, so a layout of n names costs about n × places,
// not n².

/** Pixels between a thing's centre and its name's box: clear of a robot's triangle (14 px long). */
export const GAP_PX = 12;
/** Pixels each further ring of places lies out. */
export const RING_STEP_PX = 16;
/** Rings tried (the first is beside the thing); the furthest name is about 60 px away. */
export const RINGS = 4;
/** Radius in pixels of a thing's shape, kept clear of other names. */
export const BODY_PX = 10;
const CELL_PX = 64;
/**
 * Names placed at most in one layout: 300 names 20 px apart take 13–18 ms (node, the 2-core test
 * machine), 1,000 of them 140–150 ms, too long for a frame; and more names than this in one view
 * are not read anyway. The rest wait for a zoom.
 */
export const MAX_NAMES = 300;

/** The eight directions (x right, y down), in the order a name tries them when it has no favourite. */
export const DIRECTIONS = {
  ne: [1, -1], se: [1, 1], e: [1, 0], nw: [-1, -1], sw: [-1, 1], w: [-1, 0], n: [0, -1], s: [0, 1],
};

/** The first place each kind tries: a robot's name above right, a group's below left, others below right. */
export const FAVOURITE = { mobile_robot: 'ne', group: 'sw', other: 'se' };

class BoxGrid {
  constructor() {
    this.cells = new Map();
    this.asked = 0; // which overlap() call a box was last counted in (a box may lie in 4 cells)
  }

  *cellsOf([left, top, right, bottom]) {
    for (let cx = Math.floor(left / CELL_PX); cx <= Math.floor(right / CELL_PX); cx += 1) {
      for (let cy = Math.floor(top / CELL_PX); cy <= Math.floor(bottom / CELL_PX); cy += 1) yield `${cx},${cy}`;
    }
  }

  add(box, owner) {
    for (const key of this.cellsOf(box)) {
      let list = this.cells.get(key);
      if (!list) this.cells.set(key, (list = []));
      list.push({ box, owner });
    }
  }

  /** The area of `box` covered by boxes filed here that are not `owner`'s. */
  overlap(box, owner) {
    let area = 0;
    const asked = (this.asked += 1);
    for (const key of this.cellsOf(box)) {
      for (const entry of this.cells.get(key) ?? []) {
        if (entry.owner === owner || entry.asked === asked) continue;
        entry.asked = asked;
        const w = Math.min(box[2], entry.box[2]) - Math.max(box[0], entry.box[0]);
        const h = Math.min(box[3], entry.box[3]) - Math.max(box[1], entry.box[1]);
        if (w > 0 && h > 0) area += w * h;
      }
    }
    return area;
  }
}

function order(favourite) {
  const names = Object.keys(DIRECTIONS);
  const first = names.indexOf(favourite);
  return first < 0 ? names : [names[first], ...names.filter((n) => n !== names[first])];
}

/**
 * Places for names: `items` are {id, x, y, width, height, kind} (the thing's centre and its
 * name's size, px); answers a Map id → {left, top, width, height, leader} with the name's box
 * (`leader`: drawn away from its thing, so a line should join them), or {hidden: true} for the
 * items past `most` (not placed: too many to read). Items earlier in the list choose first (the
 * selected thing's name, say).
 */
export function placeLabels(items, most = MAX_NAMES) {
  const grid = new BoxGrid();
  for (const item of items) {
    grid.add([item.x - BODY_PX, item.y - BODY_PX, item.x + BODY_PX, item.y + BODY_PX], item.id);
  }
  const placed = new Map();
  for (const item of items.slice(most)) placed.set(item.id, { hidden: true });
  for (const item of items.slice(0, most)) {
    const { x, y, width, height } = item;
    let best = null;
    for (let ring = 0; ring < RINGS && !(best && best.cost === 0); ring += 1) {
      for (const name of order(FAVOURITE[item.kind] ?? FAVOURITE.other)) {
        const [ux, uy] = DIRECTIONS[name];
        const out = GAP_PX + ring * RING_STEP_PX;
        // The box's near edge (or its middle, straight up, down or sideways) lies `out` from the centre.
        const left = ux > 0 ? x + out : ux < 0 ? x - out - width : x - width / 2;
        const top = uy > 0 ? y + out - (ux === 0 ? 0 : height / 2) : uy < 0 ? y - out - height + (ux === 0 ? 0 : height / 2) : y - height / 2;
        const box = [left, top, left + width, top + height];
        // A further ring costs a little, so that of two free places the nearer wins.
        const cost = grid.overlap(box, item.id);
        if (!best || cost < best.cost) best = { box, cost, ring };
        if (cost === 0) break;
      }
    }
    grid.add(best.box, item.id);
    placed.set(item.id, {
      left: best.box[0],
      top: best.box[1],
      width,
      height,
      leader: best.ring > 0,
    });
  }
  return placed;
}

/** Whether two boxes {left, top, width, height} overlap. */
export function overlaps(a, b) {
  return a.left < b.left + b.width && b.left < a.left + a.width && a.top < b.top + b.height && b.top < a.top + a.height;
}
