// A robot's recent path on the map: the places it passed, at most TRAIL_POINTS of them and none
// older than TRAIL_MS, kept TRAIL_STEP_M apart (a robot reports its location 20 times a second;
// a point every few centimetres draws the same line). Drawn as a few polylines, the older the
// fainter. Pure: points in, polylines out.

/** Points a trail keeps at most: a robot at 0.5 m/s leaves a point every 0.1 s at most, so 20 s of driving. */
export const TRAIL_POINTS = 200;
/** Age in milliseconds past which a point is dropped: a robot that stands still loses its trail. */
export const TRAIL_MS = 60000;
/** Metres a robot must move before its trail takes a new point. */
export const TRAIL_STEP_M = 0.05;
/** Bands of age a trail is drawn in, each fainter than the one before. */
export const TRAIL_BANDS = 6;

export class Trail {
  constructor({ points = TRAIL_POINTS, ageMs = TRAIL_MS, stepM = TRAIL_STEP_M } = {}) {
    Object.assign(this, { maxPoints: points, ageMs, stepM });
    this.points = []; // {x, y, t, gap}: gap = the path is broken before this point
  }

  /**
   * The robot is at (x, y) at time `t` (ms). `gap`: what happened since the last point is unknown
   * (the stream was reconnected): the trail is not joined across it.
   */
  add(x, y, t, gap = false) {
    if (!Number.isFinite(x) || !Number.isFinite(y)) return false;
    const last = this.points.at(-1);
    if (last && !gap && Math.hypot(x - last.x, y - last.y) < this.stepM) return false;
    this.points.push({ x, y, t, gap: gap || !last });
    if (this.points.length > this.maxPoints) this.points.splice(0, this.points.length - this.maxPoints);
    return true;
  }

  /** Drop the points older than the trail keeps; true when any went. */
  prune(now) {
    const keep = this.points.findIndex((p) => now - p.t <= this.ageMs);
    const drop = keep < 0 ? this.points.length : keep;
    if (drop) this.points.splice(0, drop);
    return drop > 0;
  }

  get length() {
    return this.points.length;
  }

  /**
   * The trail as polylines: [{points: [[x, y], ...], opacity}], newest band first at full
   * strength, each older band fainter. Consecutive bands share their meeting point, so the line
   * has no holes; a gap splits it.
   */
  polylines(now, bands = TRAIL_BANDS) {
    const lines = [];
    let current = null;
    let previous = null;
    for (const p of this.points) {
      const age = Math.max(0, now - p.t);
      const band = Math.min(bands - 1, Math.floor((age / this.ageMs) * bands));
      if (!current || p.gap || band !== current.band) {
        current = { band, points: [], opacity: Number((1 - band / bands).toFixed(3)) };
        // Joined to the last point of the band before, unless the path is broken here.
        if (previous && !p.gap) current.points.push([previous.x, previous.y]);
        lines.push(current);
      }
      current.points.push([p.x, p.y]);
      previous = p;
    }
    return lines.filter((l) => l.points.length >= 2).map(({ points, opacity }) => ({ points, opacity }));
  }
}
