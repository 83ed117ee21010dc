// roslibjs (npm roslib) drives one robot through the gateway's rosbridge endpoint, as a web
// teleop page would: list the topics, read the robot's pose, send it somewhere with the moveto
// service, drive it with cmd_vel, stop it. Prints one JSON line per step; exits 1 on a failure.
// Usage: node drive.mjs ws://HOST:PORT/rosbridge ROBOT
import * as ROSLIB from "roslib";

const [url, robot] = process.argv.slice(2);
const STEP_TIMEOUT_MS = 15000;

function step(name, run) {
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error(`${name}: no answer in ${STEP_TIMEOUT_MS} ms`)), STEP_TIMEOUT_MS);
    run(
      (value) => {
        clearTimeout(timer);
        console.log(JSON.stringify({ step: name, value }));
        resolve(value);
      },
      (error) => {
        clearTimeout(timer);
        reject(new Error(`${name}: ${typeof error === "string" ? error : JSON.stringify(error)}`));
      },
    );
  });
}

function call(ros, name, serviceType, request) {
  const service = new ROSLIB.Service({ ros, name, serviceType });
  return step(`call ${name}`, (ok, fail) => service.callService(request, ok, fail));
}

function until(ros, name, messageType, accept) {
  const topic = new ROSLIB.Topic({ ros, name, messageType });
  return step(`subscribe ${name}`, (ok) =>
    topic.subscribe((message) => {
      if (accept(message)) {
        topic.unsubscribe();
        ok(message);
      }
    }),
  );
}

async function main() {
  const ros = new ROSLIB.Ros({ url });
  await step("connect", (ok, fail) => {
    ros.on("connection", () => ok(url));
    ros.on("error", (error) => fail(String(error?.message ?? error)));
  });
  const topics = await step("topics", (ok, fail) => ros.getTopics(ok, fail));
  if (!topics.topics.includes(`/${robot}/cmd_vel`)) throw new Error(`no /${robot}/cmd_vel in ${topics.topics}`);
  const type = await step("topic type", (ok, fail) => ros.getTopicType(`/${robot}/pose`, ok, fail));
  if (type !== "geometry_msgs/Pose2D") throw new Error(`/${robot}/pose is ${type}`);
  const start = await until(ros, `/${robot}/pose`, "geometry_msgs/Pose2D", () => true);
  // moveto: one metre further along x, given as the target's location.
  const target = { x: start.x + 1, y: start.y };
  await call(ros, `/${robot}/behaviors/moveto`, "propertyservice/Action", target);
  await until(ros, `/${robot}/pose`, "geometry_msgs/Pose2D", (m) => Math.abs(m.x - target.x) < 0.05);
  // cmd_vel: the robot's velocity follows while the command is renewed (its dead-man).
  const cmdVel = new ROSLIB.Topic({ ros, name: `/${robot}/cmd_vel`, messageType: "geometry_msgs/Twist" });
  const twist = { linear: { x: 0.2, y: 0, z: 0 }, angular: { x: 0, y: 0, z: 0 } };
  cmdVel.publish(twist);
  const renew = setInterval(() => cmdVel.publish(twist), 100);
  const moving = await until(ros, `/${robot}/velocity`, "std_msgs/Float64MultiArray", (m) => {
    const [vx, vy] = m.data;
    return Math.abs(Math.hypot(vx, vy) - 0.2) < 1e-6;
  });
  clearInterval(renew);
  await call(ros, `/${robot}/behaviors/stop`, "std_srvs/Trigger", {});
  await until(ros, `/${robot}/velocity`, "std_msgs/Float64MultiArray", (m) => m.data.every((v) => v === 0));
  const found = await call(ros, "/registry/find", "propertyservice/Query", { type: "mobile_robot" });
  if (!found.names.includes(robot)) throw new Error(`registry/find: ${JSON.stringify(found)}`);
  console.log(JSON.stringify({ step: "done", value: moving.data }));
  ros.close();
}

main().catch((error) => {
  console.log(JSON.stringify({ step: "failed", value: String(error?.message ?? error) }));
  process.exit(1);
});
