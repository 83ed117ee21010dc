// Driving with a gamepad (the browser's Gamepad API): the left stick drives the selected robot or
// group through the teleop (js/teleop.js), only while the dead-man button is held. Driving stops
// when the stick returns to the centre (inside the dead zone), when the dead-man button is let
// go, when the pad disconnects, and when the page loses the focus or is hidden; after a loss of
// the page the pad drives again only once its dead-man button was let go and pressed anew (a pad
// still held when the operator comes back must not start the robot by itself).
//
// The Gamepad API has no events for a stick or a button: a connected pad is read every
// POLL_MS, and only a change of what it asks is handed to the teleop (which resends a held
// command itself, as for the keys).

/** Standard mapping (w3c Gamepad, "standard"): the left shoulder button is the dead-man. */
export const DEADMAN_BUTTON = 4;
/** Standard mapping: the left stick, x right-positive and y down-positive, -1..1. */
export const STICK_X = 0;
export const STICK_Y = 1;
/**
 * A stick deflected less than this (of its reach) is at the centre: worn sticks rest a few
 * per cent off zero, and a robot must not creep on that.
 */
export const DEAD_ZONE = 0.15;
/** How often a connected pad is read: twice per teleop resend period (100 ms). */
export const POLL_MS = 50;

const pressed = (button) => Boolean(button && (typeof button === 'object' ? button.pressed : button > 0.5));

/**
 * What a pad's state asks: {forward, turn} (each -1..1, forward and counter-clockwise positive)
 * while the dead-man is held and the stick is out of the dead zone, else null. Outside the dead
 * zone the deflection is rescaled so that driving starts from 0 at its edge.
 */
export function stickCommand(pad, { deadZone = DEAD_ZONE, deadman = DEADMAN_BUTTON } = {}) {
  if (!pad || pad.connected === false || !pressed(pad.buttons?.[deadman])) return null;
  const x = Number(pad.axes?.[STICK_X]) || 0;
  const y = Number(pad.axes?.[STICK_Y]) || 0;
  const length = Math.hypot(x, y);
  if (length <= deadZone) return null;
  const reach = Math.min(1, (length - deadZone) / (1 - deadZone)) / length;
  const round = (v) => Number(v.toFixed(3)) + 0; // + 0 turns -0 into 0
  return { forward: round(-y * reach), turn: round(-x * reach) };
}

/**
 * The dead-man's memory: a pad drives only once armed, and it is disarmed by a loss of the page
 * or a disconnect; it is armed again by a reading with the dead-man let go.
 */
export class Deadman {
  constructor(options = {}) {
    this.options = options;
    this.armed = true;
  }

  /** The page or the pad was lost: nothing drives until the dead-man is let go and pressed again. */
  disarm() {
    this.armed = false;
  }

  /** The command of one reading of the pad (`focused`: the page has the focus and is shown). */
  read(pad, focused) {
    if (!focused) {
      this.disarm();
      return null;
    }
    const held = pad && pad.connected !== false && pressed(pad.buttons?.[this.options.deadman ?? DEADMAN_BUTTON]);
    if (!held) {
      this.armed = true;
      return null;
    }
    return this.armed ? stickCommand(pad, this.options) : null;
  }
}

const same = (a, b) => (a === null || b === null ? a === b : a.forward === b.forward && a.turn === b.turn);

export class GamepadDriver {
  /**
   * `drive(stick)` is the teleop's hook (Teleop.gamepad): a {forward, turn} to hold, or null to
   * let go. `page` is the window (navigator, document, events); `onPad(text)` shows which pad
   * drives.
   */
  constructor({ drive, page = globalThis, onPad = () => {}, options = {} }) {
    Object.assign(this, { drive, page, onPad });
    this.deadman = new Deadman(options);
    this.index = null; // the pad that drives: the first connected one
    this.timer = null;
    this.last = null;
    page.addEventListener('gamepadconnected', (e) => this.connected(e.gamepad));
    page.addEventListener('gamepaddisconnected', (e) => this.disconnected(e.gamepad));
    // Whether the page has the focus, from its events: a pad drives only a page the operator
    // looks at (document.hasFocus() is not kept by every headless or embedded browser).
    this.hasFocus = true;
    const lost = () => {
      this.hasFocus = false;
      this.deadman.disarm();
      this.send(null);
    };
    page.addEventListener('focus', () => {
      this.hasFocus = true;
    });
    page.addEventListener('blur', lost);
    page.addEventListener('pagehide', lost);
    page.document?.addEventListener('visibilitychange', () => {
      if (page.document.visibilityState === 'hidden') lost();
    });
    // A pad connected before the page loaded shows itself only on its next input: look now.
    for (const pad of this.pads()) if (pad) this.connected(pad);
  }

  pads() {
    try {
      return [...(this.page.navigator?.getGamepads?.() ?? [])];
    } catch {
      return []; // a page the Gamepad API is denied to (permissions policy)
    }
  }

  connected(pad) {
    if (this.index === null) this.index = pad?.index ?? this.pads().findIndex(Boolean);
    if (this.index < 0) this.index = null;
    if (this.index === null) return;
    const id = String(this.pad()?.id ?? 'connected').slice(0, 40);
    this.onPad(`gamepad ${id}: hold the left shoulder button, steer with the left stick`);
    if (this.timer === null) this.timer = setInterval(() => this.poll(), POLL_MS);
    this.poll();
  }

  disconnected(pad) {
    if (pad && this.index !== null && pad.index !== this.index) return;
    this.deadman.disarm();
    this.send(null);
    clearInterval(this.timer);
    this.timer = null;
    this.index = null;
    this.onPad('');
    const other = this.pads().find((p) => p && p.connected !== false && p.index !== pad?.index);
    if (other) this.connected(other);
  }

  pad() {
    return this.index === null ? null : (this.pads()[this.index] ?? null);
  }

  focused() {
    return this.hasFocus && this.page.document?.visibilityState !== 'hidden';
  }

  poll() {
    const pad = this.pad();
    if (!pad || pad.connected === false) {
      this.disconnected(pad ?? { index: this.index });
      return;
    }
    this.send(this.deadman.read(pad, this.focused()));
  }

  send(stick) {
    if (same(stick, this.last)) return;
    this.last = stick;
    this.drive(stick);
  }
}
