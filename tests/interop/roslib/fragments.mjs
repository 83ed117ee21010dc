// roslibjs joins the fragments the gateway splits a large message into. roslibjs's Topic asks for
// no fragment_size, so the subscribe goes through Ros.callOnConnection, roslibjs's own way to send
// an op; the joined publish op reaches the listeners of its topic name as any other. Prints it as JSON.
// Usage: node fragments.mjs ws://HOST:PORT/rosbridge TOPIC TYPE FRAGMENT_SIZE
import * as ROSLIB from "roslib";

const [url, topic, type, size] = process.argv.slice(2);
const ros = new ROSLIB.Ros({ url });
const timer = setTimeout(() => {
  console.log(JSON.stringify({ failed: "no message in 15 s" }));
  process.exit(1);
}, 15000);
ros.on("error", (error) => {
  console.log(JSON.stringify({ failed: String(error?.message ?? error) }));
  process.exit(1);
});
ros.on("connection", () => {
  ros.on(topic, (message) => {
    clearTimeout(timer);
    console.log(JSON.stringify({ message }));
    ros.close();
  });
  ros.callOnConnection({ op: "subscribe", id: "fragmented", topic, type, fragment_size: Number(size) });
});
