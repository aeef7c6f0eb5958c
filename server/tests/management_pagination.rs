//! RabbitMQ's pagination of the management API's listings (issue 29,
//! finding 6): `page`, `page_size`, `name`, `use_regex`, `sort`,
//! `sort_reverse`, the paged answer's shape and RabbitMQ's 400s. The same
//! queries go to Leveret and, differentially, to a RabbitMQ 3.10 node
//! with its management plugin (skipped loudly when it is not installed,
//! a failure under CI); the answers, with each page's objects reduced to
//! their names, must be the same (exchanges are paged by the same code as
//! vhosts, but RabbitMQ has an `amq.rabbitmq.trace` exchange Leveret has
//! not, so they are not in the table). And a page of many queues is answered
//! whole while the unpaginated listing still streams them all.

mod common;

use common::ops::{basic, request, OpsBroker};
use leveret_tests::rabbit_node::{self, RabbitNode};
use serde_json::{json, Value};
use std::net::SocketAddr;

async fn call(addr: SocketAddr, method: &str, path: &str, body: &Value) -> (u16, Value) {
    let auth = basic("guest", "guest");
    let answer = request(
        addr,
        method,
        path,
        &[
            ("Authorization", &auth),
            ("Content-Type", "application/json"),
        ],
        body.to_string().as_bytes(),
    )
    .await;
    let body = serde_json::from_slice(&answer.body).unwrap_or(Value::Null);
    (answer.status, body)
}

/// Objects reduced to their names, in a page or a plain list.
fn names_only(mut answer: Value) -> Value {
    let names = |list: &Value| -> Value {
        list.as_array()
            .map(|items| items.iter().map(|item| item["name"].clone()).collect())
            .unwrap_or(Value::Null)
    };
    if answer.get("items").is_some() {
        answer["items"] = names(&answer["items"]);
        answer
    } else if answer.is_array() {
        names(&answer)
    } else {
        answer
    }
}

/// The queries and what RabbitMQ 3.10 answers them, on a vhost `paged`
/// holding the queues pq1..pq5, pq1 with 5 messages ... pq5 with 1.
fn queries() -> Vec<(&'static str, u16, Value)> {
    let page = |items: &[&str], filtered: u64, page: u64, page_count: u64, size: u64| {
        json!({"filtered_count": filtered, "item_count": items.len(), "items": items,
               "page": page, "page_count": page_count, "page_size": size, "total_count": 5})
    };
    let invalid =
        |reason: &str| json!({"error": "invalid_pagination_parameters", "reason": reason});
    let bad = json!({"error": "bad_request", "reason": "Pagination parameters are invalid"});
    vec![
        (
            "/api/queues/paged?page=1&page_size=2",
            200,
            page(&["pq1", "pq2"], 5, 1, 3, 2),
        ),
        (
            "/api/queues/paged?page=3&page_size=2",
            200,
            page(&["pq5"], 5, 3, 3, 2),
        ),
        (
            "/api/queues/paged?page=1",
            200,
            page(&["pq1", "pq2", "pq3", "pq4", "pq5"], 5, 1, 1, 100),
        ),
        (
            "/api/queues/paged?page=1&page_size=2&name=PQ",
            200,
            page(&["pq1", "pq2"], 5, 1, 3, 2),
        ),
        (
            "/api/queues/paged?page=1&name=pq%5B24%5D&use_regex=true",
            200,
            page(&["pq2", "pq4"], 2, 1, 1, 100),
        ),
        (
            "/api/queues/paged?page=1&name=pq%5B24%5D",
            200,
            page(&[], 0, 1, 0, 100),
        ),
        (
            "/api/queues/paged?page=1&page_size=2&sort=name&sort_reverse=true",
            200,
            page(&["pq5", "pq4"], 5, 1, 3, 2),
        ),
        (
            "/api/queues/paged?page=1&page_size=3&sort=arguments.x-max-length",
            200,
            page(&["pq5", "pq4", "pq3"], 5, 1, 2, 3),
        ),
        (
            "/api/queues/paged?page_size=2&name=pq1",
            200,
            json!(["pq1", "pq2", "pq3", "pq4", "pq5"]),
        ),
        (
            "/api/queues/paged?page=9&page_size=2",
            400,
            json!({"error": "page_out_of_range", "reason": "Page out of range, page: 9 page size: 2, len: 5"}),
        ),
        (
            "/api/queues/paged?page=0&page_size=2",
            400,
            invalid("Invalid pagination parameters: page number 0, page size 2"),
        ),
        (
            "/api/queues/paged?page=1&page_size=501",
            400,
            invalid("Invalid pagination parameters: page number 1, page size 501"),
        ),
        (
            "/api/queues/paged?page=1&page_size=0",
            400,
            invalid("Invalid pagination parameters: page number 1, page size 0"),
        ),
        ("/api/queues/paged?page=abc", 400, bad.clone()),
        ("/api/queues/paged?page=1&name=(&use_regex=true", 400, bad),
        (
            "/api/vhosts?page=1&page_size=1&name=paged",
            200,
            json!({"filtered_count": 1, "item_count": 1, "items": ["paged"], "page": 1, "page_count": 1, "page_size": 1, "total_count": 2}),
        ),
        (
            "/api/connections?page=1&page_size=1",
            200,
            json!({"filtered_count": 0, "item_count": 0, "items": [], "page": 1, "page_count": 0, "page_size": 1, "total_count": 0}),
        ),
    ]
}

/// Sets up the vhost and its queues, runs the queries; returns those
/// answered otherwise than RabbitMQ, described.
async fn differences(addr: SocketAddr) -> Vec<String> {
    let (status, _) = call(addr, "PUT", "/api/vhosts/paged", &json!({})).await;
    assert!(status == 201 || status == 204, "vhost: {status}");
    for i in 1..=5 {
        // x-max-length orders them the other way round from their names.
        let body = json!({"durable": false, "arguments": {"x-max-length": 10 - i}});
        let (status, answer) = call(addr, "PUT", &format!("/api/queues/paged/pq{i}"), &body).await;
        assert_eq!(status, 201, "{answer}");
    }
    let mut wrong = Vec::new();
    for (path, status, expected) in queries() {
        let (got_status, got) = call(addr, "GET", path, &Value::Null).await;
        let got = names_only(got);
        if (got_status, &got) != (status, &expected) {
            wrong.push(format!(
                "{path}: got {got_status} {got}, RabbitMQ answers {status} {expected}"
            ));
        }
    }
    wrong
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn listings_are_paginated_as_rabbitmq_paginates_them() {
    let broker = OpsBroker::start("pagination", &[]);
    let wrong = differences(broker.http).await;
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    let path = "/api/exchanges/paged?page=2&page_size=1&name=amq.%5Bdf%5D&use_regex=true";
    let (status, exchanges) = call(broker.http, "GET", path, &Value::Null).await;
    assert_eq!(status, 200);
    assert_eq!(
        names_only(exchanges),
        json!({"filtered_count": 2, "item_count": 1, "items": ["amq.fanout"], "page": 2,
               "page_count": 2, "page_size": 1, "total_count": 6})
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmq_paginates_as_the_table_says() {
    if !rabbit_node::installed() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("leveret-mgmt-paged-{}", std::process::id()));
    let node = tokio::task::spawn_blocking(move || {
        RabbitNode::start_with_management("mgmt-pagination", &dir, &dir)
    })
    .await
    .expect("start the node");
    let addr = SocketAddr::from(([127, 0, 0, 1], node.management_port.expect("management")));
    let wrong = differences(addr).await;
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_page_of_many_queues_and_the_whole_stream_agree() {
    let broker = OpsBroker::start("many-paged", &[]);
    let count = 1200;
    for i in 0..count {
        let (status, _) = call(
            broker.http,
            "PUT",
            &format!("/api/queues/%2F/q{i:05}"),
            &json!({"durable": false}),
        )
        .await;
        assert_eq!(status, 201);
    }
    let (status, all) = call(broker.http, "GET", "/api/queues", &Value::Null).await;
    assert_eq!(status, 200);
    assert_eq!(all.as_array().map(Vec::len), Some(count));
    let (status, last) = call(
        broker.http,
        "GET",
        "/api/queues?page=3&page_size=500",
        &Value::Null,
    )
    .await;
    assert_eq!(status, 200, "{last}");
    assert_eq!(last["item_count"], 200);
    assert_eq!(last["page_count"], 3);
    assert_eq!(last["items"][0]["name"], "q01000");
    // Seen once under heavy load (cause not found): name what differs.
    let (paged, listed) = (&last["items"][0], &all[1000]);
    let differing: Vec<&String> = paged
        .as_object()
        .into_iter()
        .flatten()
        .filter(|(key, value)| listed.get(key.as_str()) != Some(value))
        .map(|(key, _)| key)
        .collect();
    assert_eq!(
        paged, listed,
        "a page's objects are the listing's; these keys differ: {differing:?}"
    );
}
