// Teleoperation (#teleop): an on-screen joystick and the keyboard (WASD / arrows) drive the
// selected robot or group by Setting `velocity` (vx vy vz wx wy wz, world frame). A robot stops
// by itself `velocity_timeout` (0.5 s) after the last Set, so the command is sent again every
// SEND_PERIOD_MS while held; releasing sends zeros at once, and so does losing the page (blur,
// hidden, pagehide: a keepalive request that outlives the page).

import { setProperty } from './api.js';
import { formatVector } from './values.js';

/** Resend period while held: five renewals per default velocity_timeout of 0.5 s. */
export const SEND_PERIOD_MS = 100;
const ZERO = [0, 0, 0, 0, 0, 0];
const KEYS = {
  w: 'forward', arrowup: 'forward',
  s: 'back', arrowdown: 'back',
  a: 'left', arrowleft: 'left',
  d: 'right', arrowright: 'right',
};

/**
 * The velocity 6-vector for a stick deflection. `forward` and `turn` are -1..1 (forward and
 * counter-clockwise positive). In "heading" mode the robot drives along its heading `yaw` and
 * turns; in "map" mode the stick is the map: up is +y, right is +x, no turning.
 */
export function velocityFor({ forward, turn, mode, yaw = 0, speed, turnRate }) {
  const round = (x) => Number(x.toFixed(4)) + 0; // + 0 turns -0 into 0
  if (mode === 'map') return [round(-turn * speed), round(forward * speed), 0, 0, 0, 0];
  return [round(Math.cos(yaw) * forward * speed), round(Math.sin(yaw) * forward * speed), 0, 0, 0, round(turn * turnRate)];
}

/**
 * Where the joystick's knob stands for the keys held: [dx, dy], each -1..1 of the stick's
 * reach (right and down positive, as on the screen), a diagonal kept inside the circle.
 */
export function knobForKeys(keys) {
  let dx = 0;
  let dy = 0;
  if (keys.has('forward')) dy -= 1;
  if (keys.has('back')) dy += 1;
  if (keys.has('left')) dx -= 1;
  if (keys.has('right')) dx += 1;
  const length = Math.hypot(dx, dy);
  return length > 1 ? [dx / length, dy / length] : [dx + 0, dy + 0];
}

export class Teleop {
  /**
   * `els`: {root, joystick, knob, status, speed, turn, mode, stop, target}; `selected()` the
   * selected service ({name, type}); `poseOf(name)` its last location vector; `onDrive(name)`
   * hears when driving a service begins (a velocity command ends its moveto).
   */
  constructor(els, { selected, poseOf, onDrive = () => {}, setVelocity = sendVelocity, page = globalThis }) {
    Object.assign(this, { els, selected, poseOf, onDrive, setVelocity, page });
    this.keys = new Set();
    this.stick = null; // {forward, turn} while the joystick is held
    this.pad = null; // {forward, turn} while a gamepad asks for it (js/gamepad.js)
    this.timer = null;
    this.inFlight = false;
    this.driving = null; // the service the last non-zero command went to
    this.lastSent = null;
    this._bindJoystick();
    this._bindKeys();
    this._bindPage();
    els.stop.addEventListener('click', () => this.release(true));
    // Until the operator picks a stick mode, each selection gets its kind's default: a mode that
    // differs from the one a selection last set is the operator's, and stays.
    this.modeSet = els.mode.value;
    this.modeChosen = false;
  }

  target() {
    const s = this.selected();
    return s && (s.type === 'mobile_robot' || s.type === 'group') ? s : null;
  }

  /** The selection changed: stop what was driven, show what will be. */
  selectionChanged() {
    this.keys.clear();
    this.stick = null;
    this.pad = null;
    this.showKeys();
    this.release();
    this.showStatus('', false); // the status is the selected robot's: what the last one heard goes
    const t = this.target();
    this.els.target.textContent = t ? `${t.name} (${t.type === 'group' ? 'group' : 'robot'})` : 'no robot selected';
    this.els.root.classList.toggle('disabled', !t);
    // A group has no heading; a robot drives along its own unless the operator chose the map.
    if (this.els.mode.value !== this.modeSet) this.modeChosen = true;
    if (t?.type === 'group' && this.els.mode.value === 'heading') this.els.mode.value = 'map';
    else if (t?.type === 'mobile_robot' && !this.modeChosen) this.els.mode.value = 'heading';
    this.modeSet = this.els.mode.value;
  }

  // -- input ---------------------------------------------------------------------------------

  _bindJoystick() {
    const { joystick } = this.els;
    let pointer = null; // the pointer holding the stick
    const update = (e) => {
      const rect = joystick.getBoundingClientRect();
      const radius = rect.width / 2;
      let dx = (e.clientX - rect.left - radius) / radius;
      let dy = (e.clientY - rect.top - radius) / radius;
      const length = Math.hypot(dx, dy);
      if (length > 1) {
        dx /= length;
        dy /= length;
      }
      this.moveKnob(dx, dy);
      this.stick = { forward: -dy, turn: -dx };
      this.hold();
    };
    joystick.addEventListener('pointerdown', (e) => {
      if (!this.target() || pointer !== null) return;
      pointer = e.pointerId;
      try {
        joystick.setPointerCapture(e.pointerId); // keep the stick while the pointer leaves it
      } catch {
        // a pointer the browser does not track (a synthetic event): held all the same
      }
      joystick.classList.add('active');
      update(e);
    });
    joystick.addEventListener('pointermove', (e) => {
      if (e.pointerId === pointer) update(e);
    });
    const end = (e) => {
      if (e.pointerId !== pointer) return;
      pointer = null;
      joystick.classList.remove('active');
      this.stick = null;
      this.showKeys(); // the keys still held, or the centre
      if (this.keys.size || this.pad) this.hold();
      else this.release();
    };
    joystick.addEventListener('pointerup', end);
    joystick.addEventListener('pointercancel', end);
    joystick.addEventListener('lostpointercapture', end);
  }

  _bindKeys() {
    this.page.addEventListener('keydown', (e) => {
      const key = KEYS[e.key.toLowerCase()];
      if (!key || e.ctrlKey || e.metaKey || e.altKey || isTyping(e.target) || !this.target()) return;
      e.preventDefault(); // arrows would scroll the page
      if (this.keys.has(key)) return; // the key's auto-repeat: the timer already resends
      this.keys.add(key);
      this.showKeys();
      this.hold();
    });
    this.page.addEventListener('keyup', (e) => {
      const key = KEYS[e.key.toLowerCase()];
      if (!key || !this.keys.delete(key)) return;
      this.showKeys();
      if (this.keys.size || this.stick || this.pad) this.hold();
      else this.release();
    });
  }

  /**
   * The gamepad's hook: `stick` ({forward, turn}) is held and driven like the on-screen stick;
   * null lets go (the pad's stick centred, its dead-man released, the pad gone).
   */
  gamepad(stick) {
    this.pad = stick && this.target() ? stick : null;
    if (this.pad) this.hold();
    else if (!this.keys.size && !this.stick) this.release();
  }

  _bindPage() {
    const lost = () => {
      this.keys.clear();
      this.stick = null;
      this.pad = null;
      this.showKeys();
      // Only a robot this page drives is stopped: losing focus must not end another's moveto.
      this.release(false, true);
    };
    this.page.addEventListener('blur', lost);
    this.page.addEventListener('pagehide', lost);
    this.page.document?.addEventListener('visibilitychange', () => {
      if (this.page.document.visibilityState === 'hidden') lost();
    });
  }

  /** Put the knob at [dx, dy] of the stick's reach (0, 0: the centre). */
  moveKnob(dx, dy) {
    const radius = (this.els.joystick.getBoundingClientRect?.().width ?? 0) / 2;
    this.els.knob.style.transform =
      dx === 0 && dy === 0 ? '' : `translate(${dx * radius * 0.6}px, ${dy * radius * 0.6}px)`;
  }

  /** Driving with the keys moves the knob as the stick would be held; the stick, when held, wins. */
  showKeys() {
    if (this.stick) return;
    const [dx, dy] = knobForKeys(this.keys);
    this.moveKnob(dx, dy);
    this.els.joystick.classList?.toggle('keys', this.keys.size > 0);
  }

  // -- commands ------------------------------------------------------------------------------

  /** The command held now, or null when nothing is held. */
  command() {
    let forward = 0;
    let turn = 0;
    if (this.stick) ({ forward, turn } = this.stick);
    if (this.pad) {
      forward += this.pad.forward;
      turn += this.pad.turn;
    }
    if (this.keys.has('forward')) forward += 1;
    if (this.keys.has('back')) forward -= 1;
    if (this.keys.has('left')) turn += 1;
    if (this.keys.has('right')) turn -= 1;
    if (!this.stick && !this.pad && !this.keys.size) return null;
    const t = this.target();
    if (!t) return null;
    const pose = this.poseOf(t.name);
    return velocityFor({
      forward: Math.max(-1, Math.min(1, forward)),
      turn: Math.max(-1, Math.min(1, turn)),
      mode: this.els.mode.value,
      yaw: pose && pose.length >= 6 ? pose[5] : 0,
      speed: Number(this.els.speed.value) || 0,
      turnRate: Number(this.els.turn.value) || 0,
    });
  }

  /** Something is held: send now, and every SEND_PERIOD_MS until released. */
  hold() {
    this.tick();
    if (this.timer === null) this.timer = setInterval(() => this.tick(), SEND_PERIOD_MS);
  }

  tick() {
    const velocity = this.command();
    const t = this.target();
    if (!velocity || !t) {
      this.release();
      return;
    }
    // One request at a time: a slow gateway gets the latest command next tick, never a queue.
    if (this.inFlight) return;
    if (this.driving !== t.name) this.onDrive(t.name);
    this.driving = t.name;
    this.send(t.name, velocity);
  }

  async send(name, velocity, keepalive = false) {
    const text = formatVector(velocity);
    const stopping = velocity.every((v) => v === 0);
    if (!stopping) this.inFlight = true;
    try {
      await this.setVelocity(name, text, keepalive);
      this.lastSent = text;
      this.showStatusOf(name, `${stopping ? 'stopped' : 'driving'} ${name}: velocity ${text}`, false);
    } catch (e) {
      this.showStatusOf(name, `${name}: velocity ${text}: ${e.code}: ${e.message}`, true);
    } finally {
      if (!stopping) {
        this.inFlight = false;
        // A command that was still on its way when the operator let go may land after the
        // stop: stop once more, so the robot is not left driving until its timeout.
        if (this.timer === null && this.driving === null) this.send(name, ZERO, keepalive);
      }
    }
  }

  /** Nothing is held: stop the resends and send zeros at once (also when `force`d). */
  release(force = false, keepalive = false) {
    if (this.timer !== null) {
      clearInterval(this.timer);
      this.timer = null;
    }
    const name = this.driving ?? (force ? this.target()?.name : null);
    this.driving = null;
    if (name) this.send(name, ZERO, keepalive);
  }

  showStatus(text, isError) {
    this.els.status.textContent = text;
    this.els.status.classList.toggle('error-text', isError);
  }

  /** Show what `name` answered, if it is still the one selected (a stop sent on leaving it is not). */
  showStatusOf(name, text, isError) {
    if (this.target()?.name === name) this.showStatus(text, isError);
  }
}

/** Set `velocity` of `name` (keepalive: the request outlives the page). */
function sendVelocity(name, text, keepalive) {
  return setProperty(name, 'velocity', text, {}, { keepalive });
}

function isTyping(el) {
  return Boolean(el?.isContentEditable) || ['INPUT', 'TEXTAREA', 'SELECT'].includes(el?.tagName);
}

// -- Stop all ---------------------------------------------------------------------------------
// One action that reaches every service the teleop can drive (every robot and group listed),
// after the operator confirmed it: zeros sent to each, a few at a time, and a report of which
// stopped and which did not answer.

/** Stops in flight at once: a fleet of hundreds is stopped in waves, never hundreds of requests at once. */
export const STOP_ALL_AT_ONCE = 16;

/** The services `services` ({name, type}) that Stop all reaches: robots and groups, by name. */
export function drivableNames(services) {
  return services
    .filter((s) => s.type === 'mobile_robot' || s.type === 'group')
    .map((s) => s.name)
    .sort((a, b) => a.localeCompare(b, undefined, { numeric: true }));
}

/**
 * Send zeros to the `velocity` of every one of `names`, at most `atOnce` at a time; resolves to
 * {stopped: [name], failed: [{name, error}]} in the order of `names`.
 */
export async function stopEvery(names, { setVelocity = sendVelocity, atOnce = STOP_ALL_AT_ONCE } = {}) {
  const zero = formatVector(ZERO);
  const results = new Array(names.length);
  let next = 0;
  const worker = async () => {
    while (next < names.length) {
      const at = next++;
      try {
        await setVelocity(names[at], zero, false);
        results[at] = { name: names[at] };
      } catch (error) {
        results[at] = { name: names[at], error };
      }
    }
  };
  await Promise.all(Array.from({ length: Math.min(atOnce, names.length) }, worker));
  return {
    stopped: results.filter((r) => !r.error).map((r) => r.name),
    failed: results.filter((r) => r.error).map(({ name, error }) => ({ name, error })),
  };
}

/** The report of a Stop all, as the page shows it. */
export function stopAllReport({ stopped, failed }) {
  const parts = [`Stop all: ${stopped.length} of ${stopped.length + failed.length} stopped`];
  if (stopped.length) parts.push(`stopped ${stopped.join(', ')}`);
  if (failed.length) {
    parts.push(`no answer from ${failed.map(({ name, error }) => `${name} (${error?.code ?? 'UNKNOWN'}: ${error?.message ?? error})`).join(', ')}`);
  }
  return parts.join('; ');
}

/**
 * The Stop all button: `els` {button, status}; `services()` the listed services; `teleop` the
 * page's Teleop (its own driving ends first); `confirm(text)` asks the operator.
 */
export class StopAll {
  constructor(els, { services, teleop, confirm = (text) => globalThis.confirm(text), setVelocity = sendVelocity }) {
    Object.assign(this, { els, services, teleop, confirm, setVelocity });
    this.running = false;
    els.button.addEventListener('click', () => this.run());
  }

  async run() {
    if (this.running) return; // one at a time: a second press while it runs adds nothing
    const names = drivableNames(this.services());
    if (!names.length) {
      this.show('Stop all: no robot or group is listed', false, [], []);
      return;
    }
    if (!this.confirm(`Stop every robot and group (${names.length}: ${names.join(', ')})?`)) return;
    this.running = true;
    this.els.button.disabled = true;
    // The page's own driving ends first, so that no renewal follows the stop.
    this.teleop.keys.clear();
    this.teleop.stick = null;
    this.teleop.showKeys();
    this.teleop.release();
    this.show(`Stop all: stopping ${names.length}…`, false, [], []);
    try {
      const result = await stopEvery(names, { setVelocity: this.setVelocity });
      this.show(stopAllReport(result), result.failed.length > 0, result.stopped, result.failed.map((f) => f.name));
    } finally {
      this.running = false;
      this.els.button.disabled = false;
    }
  }

  show(text, isError, stopped, failed) {
    const { status } = this.els;
    status.textContent = text;
    status.classList.toggle('error-text', isError);
    status.dataset.stopped = stopped.join(' ');
    status.dataset.failed = failed.join(' ');
    status.scrollIntoView?.({ block: 'nearest' }); // below the panel's fold on a small screen
  }
}
