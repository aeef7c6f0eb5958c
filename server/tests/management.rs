//! The management HTTP API of the `leveret` binary, end to end: Debian's
//! real `rabbitmqadmin` (3.10) lists, declares, publishes, gets, purges,
//! closes and deletes against it; raw requests check the answers a
//! careless or hostile client gets (401, 404, 400, 413) and that a long
//! queue listing streams whole.

mod common;

use common::ops::{basic, request, tool_available, OpsBroker};
use futures_lite::StreamExt;
use lapin::options::{BasicConsumeOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{Connection, ConnectionProperties};
use serde_json::{json, Value};
use std::process::Command;
use std::time::Duration;

/// Runs `rabbitmqadmin` against `broker`; `None` if it is not installed.
fn rabbitmqadmin(broker: &OpsBroker, args: &[&str]) -> Option<String> {
    let port = broker.http.port().to_string();
    let output = match Command::new("rabbitmqadmin")
        .args(["-H", "127.0.0.1", "-P", &port, "-u", "guest", "-p", "guest"])
        .args(args)
        .output()
    {
        Ok(output) => output,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => panic!("cannot run rabbitmqadmin: {e}"),
    };
    assert!(
        output.status.success(),
        "rabbitmqadmin {args:?}: {}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    Some(String::from_utf8_lossy(&output.stdout).into_owned())
}

fn admin_json(broker: &OpsBroker, args: &[&str]) -> Value {
    let mut all = vec!["-f", "raw_json"];
    all.extend_from_slice(args);
    let text = rabbitmqadmin(broker, &all).expect("installed");
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
}

fn named<'a>(list: &'a Value, name: &str) -> &'a Value {
    list.as_array()
        .expect("a list")
        .iter()
        .find(|item| item["name"] == name)
        .unwrap_or_else(|| panic!("no {name} in {list}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqadmin_drives_leveret() {
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let broker = OpsBroker::start("rabbitmqadmin", &[]);
    let overview = rabbitmqadmin(&broker, &["show", "overview"]).expect("installed");
    assert!(overview.contains("leveret@"), "{overview}");
    for args in [
        &[
            "declare",
            "exchange",
            "name=orders",
            "type=direct",
            "durable=false",
        ][..],
        &[
            "declare",
            "queue",
            "name=pick",
            "durable=false",
            "arguments={\"x-max-length\": 10}",
        ],
        &[
            "declare",
            "binding",
            "source=orders",
            "destination=pick",
            "routing_key=left.#",
        ],
        &[
            "publish",
            "exchange=orders",
            "routing_key=left.#",
            "payload=one",
        ],
        &[
            "publish",
            "exchange=orders",
            "routing_key=left.#",
            "payload=two",
        ],
        &[
            "publish",
            "exchange=orders",
            "routing_key=left.#",
            "payload=three",
        ],
        &["publish", "routing_key=pick", "payload=four"],
    ] {
        rabbitmqadmin(&broker, args).expect("installed");
    }
    let unrouted = rabbitmqadmin(
        &broker,
        &[
            "publish",
            "exchange=orders",
            "routing_key=nowhere",
            "payload=x",
        ],
    )
    .expect("installed");
    assert!(unrouted.contains("NOT routed"), "{unrouted}");

    let queues = admin_json(&broker, &["list", "queues"]);
    let pick = named(&queues, "pick");
    assert_eq!(pick["messages"], 4);
    assert_eq!(pick["arguments"], json!({"x-max-length": 10}));
    assert_eq!(pick["durable"], false);
    let exchanges = admin_json(&broker, &["list", "exchanges"]);
    assert_eq!(named(&exchanges, "orders")["type"], "direct");
    let bindings = admin_json(&broker, &["list", "bindings"]);
    let binding = bindings
        .as_array()
        .unwrap()
        .iter()
        .find(|b| b["source"] == "orders")
        .expect("the binding");
    assert_eq!(binding["routing_key"], "left.#");
    assert_eq!(binding["properties_key"], "left.%23");

    let got = admin_json(
        &broker,
        &["get", "queue=pick", "count=2", "ackmode=ack_requeue_false"],
    );
    let payloads: Vec<&str> = got
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["payload"].as_str().unwrap())
        .collect();
    assert_eq!(payloads, ["one", "two"]);
    let peeked = admin_json(&broker, &["get", "queue=pick"]);
    assert_eq!(peeked[0]["payload"], "three");
    assert_eq!(peeked[0]["message_count"], 1);
    let queues = admin_json(&broker, &["list", "queues"]);
    assert_eq!(named(&queues, "pick")["messages"], 2);

    // A client: listed as a connection, channel and consumer, then closed
    // from rabbitmqadmin.
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "watch",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    let mut consumer = ch
        .basic_consume(
            "watch",
            "watcher",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");
    let connections = admin_json(&broker, &["list", "connections"]);
    let connection = &connections[0];
    assert_eq!(connection["user"], "guest");
    assert_eq!(connection["channels"], 1);
    let channels = admin_json(&broker, &["list", "channels"]);
    assert_eq!(channels[0]["consumer_count"], 1);
    let consumers = admin_json(&broker, &["list", "consumers"]);
    assert_eq!(consumers[0]["consumer_tag"], "watcher");
    assert_eq!(consumers[0]["queue"]["name"], "watch");
    let name = connection["name"].as_str().unwrap().to_owned();
    rabbitmqadmin(&broker, &["close", "connection", &format!("name={name}")]).expect("installed");
    let closed = tokio::time::timeout(Duration::from_secs(10), consumer.next()).await;
    assert!(
        matches!(closed, Ok(None) | Ok(Some(Err(_)))),
        "the consumer's connection was closed: {closed:?}"
    );
    // The client saw the close; the broker forgets the connection when its
    // task ends, right after.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while admin_json(&broker, &["list", "connections"]) != json!([]) {
        assert!(
            std::time::Instant::now() < deadline,
            "the closed connection is still listed"
        );
        std::thread::sleep(Duration::from_millis(50));
    }

    for args in [
        &["purge", "queue", "name=pick"][..],
        &[
            "delete",
            "binding",
            "source=orders",
            "destination_type=queue",
            "destination=pick",
            "properties_key=left.%23",
        ],
        &["delete", "queue", "name=pick"],
        &["delete", "queue", "name=watch"],
        &["delete", "exchange", "name=orders"],
    ] {
        rabbitmqadmin(&broker, args).expect("installed");
    }
    assert_eq!(admin_json(&broker, &["list", "queues"]), json!([]));
    let bindings = admin_json(&broker, &["list", "bindings"]);
    assert_eq!(bindings, json!([]));
    let vhosts = admin_json(&broker, &["list", "vhosts"]);
    assert_eq!(named(&vhosts, "/")["messages"], 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn careless_and_hostile_requests_get_the_right_answers() {
    let broker = OpsBroker::start("adversarial", &[]);
    let http = broker.http;
    let guest = basic("guest", "guest");
    let auth = [("Authorization", guest.as_str())];
    let json_auth = [
        ("Authorization", guest.as_str()),
        ("Content-Type", "application/json"),
    ];

    // Authentication.
    let none = request(http, "GET", "/api/overview", &[], b"").await;
    assert_eq!(none.status, 401);
    assert!(none.header("www-authenticate").is_some());
    let wrong = basic("guest", "nope");
    let wrong = request(
        http,
        "GET",
        "/api/queues",
        &[("Authorization", &wrong)],
        b"",
    )
    .await;
    assert_eq!(wrong.status, 401);
    let garbage = request(
        http,
        "GET",
        "/api/queues",
        &[("Authorization", "Basic !!!")],
        b"",
    )
    .await;
    assert_eq!(garbage.status, 401);
    let nobody = basic("nobody", "guest");
    let nobody = request(
        http,
        "DELETE",
        "/api/queues/%2F/x",
        &[("Authorization", &nobody)],
        b"",
    )
    .await;
    assert_eq!(nobody.status, 401);

    // Unknown vhosts and objects.
    for (method, path) in [
        ("GET", "/api/queues/nope"),
        ("GET", "/api/exchanges/nope"),
        ("GET", "/api/queues/%2F/missing"),
        ("GET", "/api/exchanges/%2F/missing"),
        ("DELETE", "/api/queues/%2F/missing"),
        ("DELETE", "/api/queues/nope/missing/contents"),
        ("GET", "/api/aliveness-test/nope"),
        ("GET", "/api/connections/nobody"),
        ("GET", "/api/no-such-thing"),
    ] {
        let response = request(http, method, path, &auth, b"").await;
        assert_eq!(response.status, 404, "{method} {path}: {}", response.text());
    }
    let put = request(http, "PUT", "/api/queues/nope/q", &json_auth, b"{}").await;
    assert_eq!(put.status, 404, "{}", put.text());

    // Malformed and ill-typed bodies.
    for body in [
        &b"{\"durable\": tru"[..],
        b"[1, 2, 3]",
        b"{\"durable\": 5}",
        b"{\"arguments\": [1]}",
        b"{\"arguments\": {\"x-max-length\": \"ten\"}}",
    ] {
        let response = request(http, "PUT", "/api/queues/%2F/typed", &json_auth, body).await;
        assert_eq!(
            response.status,
            400,
            "{}: {}",
            String::from_utf8_lossy(body),
            response.text()
        );
        let reason: Value = serde_json::from_slice(&response.body).expect("a JSON error");
        assert!(reason["reason"].as_str().is_some_and(|r| !r.is_empty()));
    }
    let bad_props = request(
        http,
        "POST",
        "/api/exchanges/%2F/amq.default/publish",
        &json_auth,
        br#"{"routing_key": "q", "payload": "x", "properties": {"delivery_mode": 9}}"#,
    )
    .await;
    assert_eq!(bad_props.status, 400);

    // RabbitMQ's checks, through the API.
    let created = request(
        http,
        "PUT",
        "/api/queues/%2F/q",
        &json_auth,
        br#"{"durable": false}"#,
    )
    .await;
    assert_eq!(created.status, 201);
    let again = request(
        http,
        "PUT",
        "/api/queues/%2F/q",
        &json_auth,
        br#"{"durable": false}"#,
    )
    .await;
    assert_eq!(again.status, 204);
    let inequivalent = request(
        http,
        "PUT",
        "/api/queues/%2F/q",
        &json_auth,
        br#"{"durable": true}"#,
    )
    .await;
    assert_eq!(inequivalent.status, 400);
    assert!(
        inequivalent.text().contains("inequivalent arg 'durable'"),
        "{}",
        inequivalent.text()
    );
    let reserved = request(http, "DELETE", "/api/exchanges/%2F/amq.direct", &auth, b"").await;
    // RabbitMQ's answer to a refused object operation.
    assert_eq!(reserved.status, 401, "{}", reserved.text());
    assert!(
        reserved.text().contains("Access refused."),
        "{}",
        reserved.text()
    );
    let too_many = request(
        http,
        "POST",
        "/api/queues/%2F/q/get",
        &json_auth,
        br#"{"count": 100000}"#,
    )
    .await;
    assert_eq!(too_many.status, 400);

    // Oversized bodies are refused before they are read whole.
    let huge = vec![b' '; 2 * 1024 * 1024];
    let oversized = request(
        http,
        "POST",
        "/api/exchanges/%2F/amq.default/publish",
        &json_auth,
        &huge,
    )
    .await;
    assert_eq!(oversized.status, 413);

    // Health checks.
    let alive = request(http, "GET", "/api/aliveness-test/%2F", &auth, b"").await;
    assert_eq!(alive.status, 200);
    assert_eq!(
        serde_json::from_slice::<Value>(&alive.body).unwrap()["status"],
        "ok"
    );
    let alarms = request(http, "GET", "/api/health/checks/alarms", &auth, b"").await;
    assert_eq!(alarms.status, 200);

    // A listing longer than one chunk streams whole and in order.
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    for i in 0..1200 {
        ch.queue_declare(
            &format!("many-{i:04}"),
            QueueDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("declare");
    }
    let listing = request(http, "GET", "/api/queues/%2F", &auth, b"").await;
    assert_eq!(listing.status, 200);
    let queues: Value = serde_json::from_slice(&listing.body).expect("one JSON array");
    let names: Vec<&str> = queues
        .as_array()
        .unwrap()
        .iter()
        .map(|q| q["name"].as_str().unwrap())
        .collect();
    assert_eq!(names.len(), 1202, "aliveness-test, q and 1200 more");
    assert!(names.windows(2).all(|w| w[0] < w[1]), "sorted by name");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn vhosts_per_object_bindings_and_per_vhost_definitions() {
    let broker = OpsBroker::start("vhost-defs", &[]);
    let http = broker.http;
    let guest = basic("guest", "guest");
    let auth = [
        ("Authorization", guest.as_str()),
        ("Content-Type", "application/json"),
    ];
    let send = |method: &'static str, path: &'static str, body: &'static [u8]| async move {
        request(http, method, path, &auth, body).await
    };
    assert_eq!(send("PUT", "/api/vhosts/robots", b"").await.status, 201);
    assert_eq!(send("PUT", "/api/vhosts/robots", b"").await.status, 204);
    assert_eq!(send("DELETE", "/api/vhosts/robots", b"").await.status, 204);
    assert_eq!(send("DELETE", "/api/vhosts/robots", b"").await.status, 404);
    assert_eq!(send("PUT", "/api/vhosts/robots", b"").await.status, 201);
    for (path, body) in [
        (
            "/api/exchanges/robots/sensors",
            &br#"{"type": "topic"}"#[..],
        ),
        ("/api/exchanges/robots/all", br#"{"type": "fanout"}"#),
        ("/api/queues/robots/lidar", br#"{"durable": true}"#),
    ] {
        let response = request(http, "PUT", path, &auth, body).await;
        assert_eq!(response.status, 201, "{path}: {}", response.text());
    }
    for path in [
        "/api/bindings/robots/e/sensors/q/lidar",
        "/api/bindings/robots/e/all/e/sensors",
    ] {
        let response = request(http, "POST", path, &auth, br#"{"routing_key": "lidar.#"}"#).await;
        assert_eq!(response.status, 201, "{path}: {}", response.text());
        assert_eq!(response.header("location"), Some("lidar.%23"));
    }
    let json_of = |response: common::ops::Response| -> Value {
        assert_eq!(response.status, 200, "{}", response.text());
        serde_json::from_slice(&response.body).expect("JSON")
    };
    let on_queue = json_of(send("GET", "/api/queues/robots/lidar/bindings", b"").await);
    assert_eq!(
        on_queue.as_array().unwrap().len(),
        2,
        "the default exchange's and ours: {on_queue}"
    );
    let source = json_of(send("GET", "/api/exchanges/robots/sensors/bindings/source", b"").await);
    assert_eq!(source[0]["destination"], "lidar");
    let destination = json_of(
        send(
            "GET",
            "/api/exchanges/robots/sensors/bindings/destination",
            b"",
        )
        .await,
    );
    assert_eq!(destination[0]["source"], "all");
    let missing = send("GET", "/api/exchanges/robots/nope/bindings/source", b"").await;
    assert_eq!(missing.status, 404);

    let exported = json_of(send("GET", "/api/definitions/robots", b"").await);
    assert_eq!(
        exported["queues"],
        json!([{"name": "lidar", "type": "classic", "durable": true, "auto_delete": false, "arguments": {}}])
    );
    assert!(exported.get("users").is_none() && exported.get("vhosts").is_none());
    let body = exported.to_string();
    let imported = request(http, "POST", "/api/definitions/%2F", &auth, body.as_bytes()).await;
    assert_eq!(imported.status, 200, "{}", imported.text());
    let root = json_of(send("GET", "/api/definitions/%2F", b"").await);
    for key in ["queues", "exchanges", "bindings"] {
        assert_eq!(root[key], exported[key], "{key}");
    }
    let unknown = send("GET", "/api/definitions/nowhere", b"").await;
    assert_eq!(unknown.status, 404);
}

/// A disk alarm (a `--disk-free-limit` above the disk's free space) shows
/// where operators look: the alarms health check fails with resource
/// `disk`, `/api/nodes` reports it with the limit, the Prometheus gauge is
/// 1 and the limit is exported.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disk_alarm_shows_in_the_health_check_nodes_and_metrics() {
    let limit = "1000000000000000000";
    let broker = OpsBroker::start("disk-alarm", &["--disk-free-limit", limit]);
    let guest = basic("guest", "guest");
    let auth = [("Authorization", guest.as_str())];
    let alarms = request(broker.http, "GET", "/api/health/checks/alarms", &auth, b"").await;
    assert_eq!(alarms.status, 503, "{}", alarms.text());
    let body: Value = serde_json::from_slice(&alarms.body).expect("json");
    assert_eq!(body["alarms"][0]["resource"], "disk", "{body}");
    let nodes = request(broker.http, "GET", "/api/nodes", &auth, b"").await;
    let nodes: Value = serde_json::from_slice(&nodes.body).expect("json");
    assert_eq!(nodes[0]["disk_free_alarm"], true, "{nodes}");
    assert_eq!(nodes[0]["disk_free_limit"], 1_000_000_000_000_000_000u64);
    assert_eq!(nodes[0]["mem_alarm"], false);
    let metrics = request(broker.metrics, "GET", "/metrics", &[], b"")
        .await
        .text();
    assert!(
        metrics.contains("\nrabbitmq_alarms_free_disk_space_watermark 1\n"),
        "{metrics}"
    );
    assert!(
        metrics.contains(&format!(
            "\nrabbitmq_disk_space_available_limit_bytes {limit}\n"
        )),
        "{metrics}"
    );
}

/// Permissions through the management API with rabbitmqadmin 3.10:
/// `declare permission` grants, the broker enforces it on the user's AMQP
/// operations, `list permissions` shows it and `delete permission` takes
/// it back; topic permissions through RabbitMQ's HTTP API.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqadmin_sets_permissions_the_broker_enforces() {
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("leveret-perm-config-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("leveret.toml");
    std::fs::write(
        &config,
        "[[users]]\nname = \"guest\"\npassword = \"guest\"\ntags = [\"administrator\"]\n\
         [[users.permissions]]\nvhost = \"/\"\nconfigure = \".*\"\nwrite = \".*\"\nread = \".*\"\n\n\
         [[users]]\nname = \"robot\"\npassword = \"pw\"\n",
    )
    .expect("config");
    let broker = OpsBroker::start("permissions", &["--config", config.to_str().unwrap()]);
    let robot_url = format!("amqp://robot:pw@{}/%2f", broker.amqp);
    let connect = || Connection::connect(&robot_url, ConnectionProperties::default());
    assert!(connect().await.is_err(), "no permission on / yet");

    rabbitmqadmin(
        &broker,
        &[
            "declare",
            "permission",
            "vhost=/",
            "user=robot",
            "configure=^robot\\.",
            "write=.*",
            "read=.*",
        ],
    )
    .expect("installed");
    let listed = admin_json(&broker, &["list", "permissions"]);
    assert!(
        listed
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["user"] == "robot" && p["configure"] == "^robot\\."),
        "{listed}"
    );
    let conn = connect().await.expect("granted");
    let channel = conn.create_channel().await.expect("channel");
    channel
        .queue_declare(
            "robot.q",
            QueueDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("inside configure");
    let refused = channel
        .queue_declare(
            "other",
            QueueDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect_err("outside configure");
    assert!(
        refused.to_string().contains(
            "ACCESS_REFUSED - access to queue 'other' in vhost '/' refused for user 'robot'"
        ),
        "{refused}"
    );
    // rabbitmqadmin 3.10 has no topic permissions: RabbitMQ's HTTP API.
    let guest = basic("guest", "guest");
    let put = request(
        broker.http,
        "PUT",
        "/api/topic-permissions/%2F/robot",
        &[
            ("Authorization", &guest),
            ("Content-Type", "application/json"),
        ],
        br#"{"exchange": "amq.topic", "write": "^robot\\.", "read": ".*"}"#,
    )
    .await;
    assert_eq!(put.status, 204, "{}", put.text());
    let topics = request(
        broker.http,
        "GET",
        "/api/topic-permissions",
        &[("Authorization", &guest)],
        b"",
    )
    .await;
    let topics: Value = serde_json::from_slice(&topics.body).expect("JSON");
    assert_eq!(topics[0]["exchange"], "amq.topic", "{topics}");
    assert_eq!(topics[0]["write"], "^robot\\.", "{topics}");
    // A topic exchange's routing keys are now checked.
    let topic = conn.create_channel().await.expect("channel");
    let (closed_tx, closed_rx) = std::sync::mpsc::channel();
    topic.on_error(move |error| {
        let _ = closed_tx.send(error.to_string());
    });
    topic
        .basic_publish(
            "amq.topic",
            "other.key",
            Default::default(),
            b"x",
            Default::default(),
        )
        .await
        .expect("sent");
    let closed =
        tokio::task::spawn_blocking(move || closed_rx.recv_timeout(Duration::from_secs(10)))
            .await
            .unwrap()
            .expect("the publish closed the channel");
    assert!(closed.contains("access to topic 'other.key'"), "{closed}");

    rabbitmqadmin(&broker, &["delete", "permission", "vhost=/", "user=robot"]).expect("installed");
    assert!(connect().await.is_err(), "cleared");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Users through the management API with rabbitmqadmin 3.10, as
/// RabbitMQ keeps them: `declare user` adds one with its tags, who logs in
/// over AMQP once granted a permission; the user, tags and permission
/// outlast a SIGKILL right after the answers (they were on disk before
/// them); `delete user` takes the user and their permissions away, for good.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqadmin_adds_users_that_outlast_a_crash() {
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let broker = OpsBroker::start("users", &[]);
    for args in [
        &[
            "declare",
            "user",
            "name=robot",
            "password=pw",
            "tags=monitoring",
        ][..],
        &[
            "declare",
            "permission",
            "vhost=/",
            "user=robot",
            "configure=.*",
            "write=.*",
            "read=.*",
        ],
        &["declare", "vhost", "name=cell-7"],
    ] {
        rabbitmqadmin(&broker, args).expect("installed");
    }
    let robot_url = |broker: &OpsBroker| format!("amqp://robot:pw@{}/%2f", broker.amqp);
    Connection::connect(&robot_url(&broker), ConnectionProperties::default())
        .await
        .expect("the new user logs in");
    let whoami = request(
        broker.http,
        "GET",
        "/api/whoami",
        &[("Authorization", &basic("robot", "pw"))],
        b"",
    )
    .await;
    assert_eq!(whoami.status, 200, "{}", whoami.text());
    assert!(whoami.text().contains("monitoring"), "{}", whoami.text());

    let broker = broker.kill_and_restart(&[]);
    let users = admin_json(&broker, &["list", "users"]);
    assert_eq!(
        named(&users, "robot")["tags"],
        json!(["monitoring"]),
        "{users}"
    );
    let vhosts = admin_json(&broker, &["list", "vhosts"]);
    named(&vhosts, "cell-7");
    Connection::connect(&robot_url(&broker), ConnectionProperties::default())
        .await
        .expect("the user and permission outlast the crash");

    rabbitmqadmin(&broker, &["delete", "user", "name=robot"]).expect("installed");
    let broker = broker.kill_and_restart(&[]);
    let users = admin_json(&broker, &["list", "users"]);
    assert!(
        users
            .as_array()
            .unwrap()
            .iter()
            .all(|u| u["name"] != "robot"),
        "{users}"
    );
    let permissions = admin_json(&broker, &["list", "permissions"]);
    assert!(
        permissions
            .as_array()
            .unwrap()
            .iter()
            .all(|p| p["user"] != "robot"),
        "{permissions}"
    );
    assert!(
        Connection::connect(&robot_url(&broker), ConnectionProperties::default())
            .await
            .is_err(),
        "deleted for good"
    );
    // A new user needs a password; a bad hash is refused; neither changes anything.
    let guest = basic("guest", "guest");
    let headers = [
        ("Authorization", guest.as_str()),
        ("Content-Type", "application/json"),
    ];
    for body in [
        &br#"{"tags": "administrator"}"#[..],
        br#"{"password_hash": "not base64", "tags": ""}"#,
    ] {
        let refused = request(broker.http, "PUT", "/api/users/intruder", &headers, body).await;
        assert_eq!(refused.status, 400, "{}", refused.text());
    }
    let missing = request(broker.http, "DELETE", "/api/users/intruder", &headers, b"").await;
    assert_eq!(missing.status, 404, "{}", missing.text());
    let users = admin_json(&broker, &["list", "users"]);
    assert_eq!(users.as_array().unwrap().len(), 1, "{users}");
}

/// RabbitMQ's user tags decide what a caller of the management API may see
/// and do: no management tag, no login; `management` sees only the vhosts
/// it has a permission on and cannot reach the administrator's paths;
/// `monitoring` reads everything but changes only where it has a
/// permission; `administrator` does everything and sees the tags.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn user_tags_decide_what_the_management_api_shows_and_allows() {
    let dir = std::env::temp_dir().join(format!("leveret-tags-config-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("leveret.toml");
    let full = "configure = \".*\"\nwrite = \".*\"\nread = \".*\"\n";
    std::fs::write(
        &config,
        format!(
            "vhosts = [\"/\", \"robots\"]\n\
             [[users]]\nname = \"admin\"\npassword = \"a\"\ntags = [\"administrator\"]\n\
             [[users.permissions]]\nvhost = \"/\"\n{full}\
             [[users]]\nname = \"watcher\"\npassword = \"w\"\ntags = [\"monitoring\"]\n\
             [[users]]\nname = \"robot\"\npassword = \"r\"\ntags = [\"management\"]\n\
             [[users.permissions]]\nvhost = \"robots\"\n{full}\
             [[users]]\nname = \"plain\"\npassword = \"p\"\n"
        ),
    )
    .expect("config");
    let broker = OpsBroker::start("tags", &["--config", config.to_str().unwrap()]);
    let call =
        |user: &'static str, password: &'static str, method: &'static str, path: &'static str| {
            let auth = basic(user, password);
            let http = broker.http;
            async move {
                request(
                    http,
                    method,
                    path,
                    &[
                        ("Authorization", &auth),
                        ("Content-Type", "application/json"),
                    ],
                    if method == "PUT" { b"{}" } else { b"" },
                )
                .await
            }
        };
    let refused = call("plain", "p", "GET", "/api/overview").await;
    assert_eq!(refused.status, 401, "{}", refused.text());
    assert!(refused.text().contains("Not management user"));

    assert_eq!(
        call("admin", "a", "PUT", "/api/queues/%2F/root-q")
            .await
            .status,
        201
    );
    assert_eq!(
        call("robot", "r", "PUT", "/api/queues/robots/robot-q")
            .await
            .status,
        201
    );
    let names = |response: common::ops::Response| -> Vec<String> {
        let list: Value = serde_json::from_slice(&response.body).expect("JSON");
        list.as_array()
            .unwrap()
            .iter()
            .map(|q| q["name"].as_str().unwrap().to_owned())
            .collect()
    };
    assert_eq!(
        names(call("robot", "r", "GET", "/api/queues").await),
        ["robot-q"]
    );
    let mut all = names(call("watcher", "w", "GET", "/api/queues").await);
    all.sort();
    assert_eq!(all, ["robot-q", "root-q"]);
    for (user, password, method, path, reason) in [
        (
            "robot",
            "r",
            "GET",
            "/api/queues/%2F",
            "User not authorised to access virtual host",
        ),
        ("robot", "r", "GET", "/api/users", "Not administrator user"),
        (
            "watcher",
            "w",
            "PUT",
            "/api/queues/%2F/x",
            "User not authorised to access virtual host",
        ),
        (
            "watcher",
            "w",
            "GET",
            "/api/definitions",
            "Not administrator user",
        ),
    ] {
        let answer = call(user, password, method, path).await;
        assert_eq!(
            answer.status,
            401,
            "{user} {method} {path}: {}",
            answer.text()
        );
        assert!(answer.text().contains(reason), "{}", answer.text());
    }
    let users: Value =
        serde_json::from_slice(&call("admin", "a", "GET", "/api/users").await.body).expect("JSON");
    let robot = users
        .as_array()
        .unwrap()
        .iter()
        .find(|u| u["name"] == "robot")
        .expect("robot");
    assert_eq!(robot["tags"], json!(["management"]));
    let whoami: Value =
        serde_json::from_slice(&call("watcher", "w", "GET", "/api/whoami").await.body)
            .expect("JSON");
    assert_eq!(whoami, json!({"name": "watcher", "tags": ["monitoring"]}));
    let _ = std::fs::remove_dir_all(&dir);
}

/// `rabbitmqadmin delete vhost` (issue 31): the vhost's connection is
/// closed with RabbitMQ's 320 text, its durable queue and the vhost itself
/// are gone, after a crash too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqadmin_deletes_a_vhost_and_it_stays_deleted() {
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let broker = OpsBroker::start("delete-vhost", &[]);
    for args in [
        &["declare", "vhost", "name=gone"][..],
        &[
            "declare",
            "permission",
            "vhost=gone",
            "user=guest",
            "configure=.*",
            "write=.*",
            "read=.*",
        ],
        &[
            "-V",
            "gone",
            "declare",
            "queue",
            "name=kept",
            "durable=true",
        ],
    ] {
        rabbitmqadmin(&broker, args).expect("installed");
    }
    let url = format!("amqp://guest:guest@{}/gone", broker.amqp);
    let connection = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connects to the vhost");
    let (closed_tx, mut closed) = tokio::sync::mpsc::unbounded_channel();
    connection.on_error(move |e| {
        let _ = closed_tx.send(e);
    });
    rabbitmqadmin(&broker, &["delete", "vhost", "name=gone"]).expect("installed");
    let error = tokio::time::timeout(Duration::from_secs(30), closed.recv())
        .await
        .expect("closed in time")
        .expect("an error");
    assert!(
        error
            .to_string()
            .contains("CONNECTION_FORCED - vhost 'gone' is deleted"),
        "{error}"
    );
    let missing = request(
        broker.http,
        "DELETE",
        "/api/vhosts/gone",
        &[("Authorization", &basic("guest", "guest"))],
        b"",
    )
    .await;
    assert_eq!(missing.status, 404, "{}", missing.text());

    let broker = broker.kill_and_restart(&[]);
    let vhosts = admin_json(&broker, &["list", "vhosts"]);
    assert!(
        vhosts
            .as_array()
            .expect("list")
            .iter()
            .all(|v| v["name"] != "gone"),
        "{vhosts}"
    );
    let queues = admin_json(&broker, &["list", "queues"]);
    assert!(
        queues
            .as_array()
            .expect("list")
            .iter()
            .all(|q| q["vhost"] != "gone"),
        "{queues}"
    );
}

/// RabbitMQ's parameter listings over Leveret's two components:
/// `/api/parameters` (rabbitmqadmin's `list parameters`), by component,
/// by component and vhost (404 for a vhost that does not exist, nothing
/// for a component Leveret lacks), and nothing of a vhost the caller has
/// no permission on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameters_are_listed_by_component_and_vhost() {
    let broker = OpsBroker::start("parameters", &[]);
    let guest = basic("guest", "guest");
    let auth = [("Authorization", guest.as_str())];
    let get = |path: String, auth: String| {
        let http = broker.http;
        async move {
            let response = request(http, "GET", &path, &[("Authorization", &auth)], b"").await;
            let body = serde_json::from_slice(&response.body).unwrap_or(Value::Null);
            (response.status, body)
        }
    };
    // Nowhere to connect to: the shovel and the upstream are declared and
    // keep retrying, which is all this needs.
    let shovel = json!({"value": {"src-uri": "amqp://127.0.0.1:1", "src-queue": "a",
        "dest-uri": "amqp://127.0.0.1:1", "dest-queue": "b"}});
    let put = request(
        broker.http,
        "PUT",
        "/api/parameters/shovel/%2F/mover",
        &auth,
        shovel.to_string().as_bytes(),
    )
    .await;
    assert_eq!(put.status, 201, "{}", put.text());
    let upstream = json!({"value": {"uri": "amqp://127.0.0.1:1"}});
    let put = request(
        broker.http,
        "PUT",
        "/api/parameters/federation-upstream/%2F/far",
        &auth,
        upstream.to_string().as_bytes(),
    )
    .await;
    assert!(put.status == 201 || put.status == 204, "{}", put.text());

    let (status, all) = get("/api/parameters".into(), guest.clone()).await;
    assert_eq!(status, 200);
    let mut seen: Vec<(String, String, String)> = all
        .as_array()
        .expect("a list")
        .iter()
        .map(|p| {
            assert!(p["value"].is_object(), "{p}");
            let text = |key: &str| p[key].as_str().expect(key).to_owned();
            (text("component"), text("vhost"), text("name"))
        })
        .collect();
    seen.sort();
    assert_eq!(
        seen,
        [
            ("federation-upstream".into(), "/".into(), "far".into()),
            ("shovel".into(), "/".into(), "mover".into())
        ]
    );
    assert_eq!(
        named(&all, "mover")["value"]["dest-queue"],
        "b",
        "the value as given"
    );

    let (_, shovels) = get("/api/parameters/shovel".into(), guest.clone()).await;
    assert_eq!(shovels.as_array().map(Vec::len), Some(1), "{shovels}");
    assert_eq!(shovels[0]["name"], "mover");
    let (_, upstreams) = get(
        "/api/parameters/federation-upstream/%2F".into(),
        guest.clone(),
    )
    .await;
    assert_eq!(upstreams.as_array().map(Vec::len), Some(1), "{upstreams}");
    assert_eq!(upstreams[0]["name"], "far");
    let (status, none) = get("/api/parameters/no-such-component".into(), guest.clone()).await;
    assert_eq!((status, none), (200, json!([])));
    let (status, _) = get("/api/parameters/shovel/no-such-vhost".into(), guest.clone()).await;
    assert_eq!(status, 404);

    // A management user without a permission on `/` sees none of it.
    let user = br#"{"password": "pw", "tags": "management"}"#;
    let added = request(broker.http, "PUT", "/api/users/viewer", &auth, user).await;
    assert!(added.status < 300, "{}", added.text());
    let (status, hidden) = get("/api/parameters".into(), basic("viewer", "pw")).await;
    assert_eq!((status, hidden), (200, json!([])));

    if tool_available("rabbitmqadmin", "rabbitmq-server") {
        let listed = admin_json(&broker, &["list", "parameters"]);
        assert_eq!(listed.as_array().map(Vec::len), Some(2), "{listed}");
    }
}
