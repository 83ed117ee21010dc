// The example page's behaviour, written only against roslibjs's documented API: a ROSLIB.Ros
// connection to the gateway's rosbridge endpoint, ros.getTopics for the list, a ROSLIB.Topic
// subscription for the location, a ROSLIB.Topic publishing geometry_msgs/Twist on cmd_vel, and a
// ROSLIB.Service call of the robot's moveto behaviour. Nothing here knows it talks to a gateway.
"use strict";

(() => {
  // How often a held joystick repeats its command: the robot stops when commands stop coming
  // (its velocity_timeout), so a held stick must renew well within it. 10 Hz is teleop's usual rate.
  const PUBLISH_PERIOD_MS = 100;
  // Full deflection of the stick: m/s forward and rad/s of turn (the simulated robots clip to theirs).
  const MAX_LINEAR = 0.5;
  const MAX_ANGULAR = 1.0;

  const $ = (id) => document.getElementById(id);
  const status = $("status");
  const robotSelect = $("robot");
  const locationOut = $("location");
  const twistOut = $("twist");
  const joystick = $("joystick");
  const knob = $("knob");

  const setStatus = (state, text) => {
    status.dataset.state = state;
    status.textContent = text;
  };

  if (typeof ROSLIB === "undefined") {
    setStatus("error", "roslibjs is missing: run `npm ci` in this page's folder (see its source)");
    return;
  }

  const scheme = window.location.protocol === "https:" ? "wss" : "ws";
  const ros = new ROSLIB.Ros({ url: `${scheme}://${window.location.host}/rosbridge` });

  let topicTypes = new Map();
  let robot = null;
  let locationTopic = null;
  let cmdVel = null;

  ros.on("connection", () => {
    setStatus("connected", "connected");
    listTopics();
  });
  ros.on("error", () => setStatus("error", "connection error"));
  ros.on("close", () => setStatus("error", "connection closed"));

  // -- the topic list, and the robots found in it -----------------------------------------------
  function listTopics() {
    ros.getTopics(
      (result) => {
        topicTypes = new Map(result.topics.map((name, i) => [name, result.types[i] || ""]));
        const list = $("topics");
        list.replaceChildren(
          ...result.topics.map((name) => {
            const item = document.createElement("li");
            item.textContent = `${name}  ${topicTypes.get(name)}`;
            item.dataset.topic = name;
            return item;
          }),
        );
        fillRobots(result.topics);
      },
      (error) => setStatus("error", `getTopics failed: ${error}`),
    );
  }

  // A robot is a namespace with a velocity or cmd_vel topic right under it: /<robot>/cmd_vel.
  function fillRobots(topics) {
    const robots = new Set();
    for (const name of topics) {
      const m = /^\/([^/]+)\/(cmd_vel|velocity)$/.exec(name);
      if (m) robots.add(m[1]);
    }
    const wanted = new URLSearchParams(window.location.search).get("robot");
    robotSelect.replaceChildren(
      ...[...robots].sort().map((name) => {
        const option = document.createElement("option");
        option.value = option.textContent = name;
        return option;
      }),
    );
    if (wanted && robots.has(wanted)) robotSelect.value = wanted;
    chooseRobot(robotSelect.value || null);
  }

  robotSelect.addEventListener("change", () => chooseRobot(robotSelect.value));

  function chooseRobot(name) {
    stopDriving();
    if (locationTopic) locationTopic.unsubscribe();
    if (cmdVel) cmdVel.unadvertise();
    robot = name;
    locationTopic = cmdVel = null;
    locationOut.textContent = "—";
    if (!robot) return;

    // The robot's location as a geometry_msgs/Pose2D (x, y, theta), at most 10 a second.
    const poseName = `/${robot}/location`;
    locationOut.dataset.topic = poseName;
    locationTopic = new ROSLIB.Topic({
      ros,
      name: poseName,
      messageType: "geometry_msgs/Pose2D",
      throttle_rate: 100,
      queue_length: 1,
    });
    locationTopic.subscribe((message) => {
      locationOut.textContent = describePosition(message);
    });
    cmdVel = new ROSLIB.Topic({ ros, name: `/${robot}/cmd_vel`, messageType: "geometry_msgs/Twist" });
  }

  // A geometry_msgs/Pose2D as the readout shows it.
  function describePosition(pose) {
    const fixed = (v) => Number(v).toFixed(2);
    return `x ${fixed(pose.x)} y ${fixed(pose.y)} θ ${fixed(pose.theta)}`;
  }

  // -- the joystick: drag to drive, let go to stop ------------------------------------------------
  let stick = { x: 0, y: 0 }; // -1..1 each, y up
  let publishTimer = null;

  const twistOf = ({ x, y }) => ({
    linear: { x: y * MAX_LINEAR, y: 0, z: 0 },
    angular: { x: 0, y: 0, z: -x * MAX_ANGULAR },
  });

  function publishStick() {
    if (!cmdVel) return;
    const twist = twistOf(stick);
    cmdVel.publish(new ROSLIB.Message(twist));
    twistOut.textContent = `${twist.linear.x.toFixed(2)} ${twist.angular.z.toFixed(2)}`;
  }

  function moveStick(event) {
    const box = joystick.getBoundingClientRect();
    const radius = box.width / 2;
    let dx = (event.clientX - box.left - radius) / radius;
    let dy = (event.clientY - box.top - radius) / radius;
    const length = Math.hypot(dx, dy);
    if (length > 1) {
      dx /= length;
      dy /= length;
    }
    stick = { x: dx, y: -dy };
    const knobRadius = knob.offsetWidth / 2;
    knob.style.left = `${radius + dx * radius - knobRadius}px`;
    knob.style.top = `${radius + dy * radius - knobRadius}px`;
  }

  function stopDriving() {
    const wasDriving = publishTimer !== null;
    clearInterval(publishTimer);
    publishTimer = null;
    stick = { x: 0, y: 0 };
    knob.style.left = knob.style.top = "";
    joystick.dataset.held = "false";
    if (wasDriving) publishStick(); // one zero Twist: stop now rather than at the robot's timeout
  }

  joystick.addEventListener("pointerdown", (event) => {
    if (!cmdVel) return;
    joystick.setPointerCapture(event.pointerId);
    joystick.dataset.held = "true";
    moveStick(event);
    publishStick();
    publishTimer = setInterval(publishStick, PUBLISH_PERIOD_MS);
  });
  joystick.addEventListener("pointermove", (event) => {
    if (publishTimer !== null) moveStick(event);
  });
  for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
    joystick.addEventListener(type, stopDriving);
  }
  window.addEventListener("blur", stopDriving);

  // -- moveto: the robot's behaviour, called as a ROS service -----------------------------------
  $("moveto").addEventListener("click", () => {
    if (!robot) return;
    const result = $("moveto-result");
    const x = Number($("target-x").value);
    const y = Number($("target-y").value);
    const service = new ROSLIB.Service({
      ros,
      name: `/${robot}/behaviors/moveto`,
      serviceType: "propertyservice/Action", // what /rosapi/service_type says of an action
    });
    result.dataset.state = "calling";
    result.textContent = "calling…";
    service.callService(
      new ROSLIB.ServiceRequest({ x, y }), // the target as a point, as ROS's go-to services take it
      () => {
        result.dataset.state = "ok";
        result.textContent = `moving to ${x} ${y}`;
      },
      (error) => {
        result.dataset.state = "error";
        result.textContent = `refused: ${error}`;
      },
    );
  });
})();
