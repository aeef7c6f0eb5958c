//! Smoke tests: each subcommand runs briefly against a Leveret broker
//! started in-process on port 0 and completes; the broadcast-quality run
//! loses nothing. No timing is asserted (benchmarks never are).

use clap::Parser;
use leveret_broker::{Broker, BrokerHandle};
use leveret_perf::cli::{execute, Cli, Command};
use leveret_perf::load::ExchangeKind;
use leveret_perf::{compare, memory, ports, quality, rtt, throughput};
use std::path::PathBuf;

async fn broker() -> (BrokerHandle, String) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("broker starts");
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    (handle, url)
}

fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("leveret-perf-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn throughput_from_the_command_line() {
    let (handle, url) = broker().await;
    let cli = Cli::try_parse_from([
        "leveret-perf",
        "throughput",
        "--url",
        &url,
        "--duration",
        "1",
        "--warmup",
        "0",
    ])
    .unwrap();
    execute(&cli.command).await.unwrap();
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn throughput_with_confirms_acks_and_fanout() {
    let (handle, url) = broker().await;
    let dir = scratch_dir("throughput");
    let args = throughput::ThroughputArgs {
        url: url.clone(),
        publishers: 2,
        consumers: 2,
        queues: 2,
        persistent: true,
        confirm: 64,
        ack: true,
        prefetch: 100,
        multi_ack: 10,
        duration: 0.5,
        warmup: 0.2,
        json: Some(dir.join("t.json")),
        quiet: true,
        ..Default::default()
    };
    let report = throughput::run(&args).await.unwrap();
    assert!(report.published > 0);
    assert!(report.drained);
    assert_eq!(report.totals.lost, 0);
    assert_eq!(report.totals.duplicates, 0);
    assert_eq!(report.acked, report.published);
    let confirms = report
        .confirm_latency
        .expect("confirm latency with confirms");
    assert!(confirms.count > 0 && confirms.p50_us > 0.0 && confirms.p99_us >= confirms.p50_us);
    assert!(dir.join("t.json").exists());

    let fanout = throughput::ThroughputArgs {
        url,
        exchange: ExchangeKind::Fanout,
        queues: 4,
        consumers: 4,
        size: 64,
        rate: 2000.0,
        duration: 0.5,
        warmup: 0.0,
        quiet: true,
        ..Default::default()
    };
    let report = throughput::run(&fanout).await.unwrap();
    assert!(
        report.confirm_latency.is_none(),
        "no confirms, no confirm latency"
    );
    assert!(report.drained);
    assert_eq!(report.totals.lost, 0);
    assert_eq!(report.totals.gaps + report.totals.out_of_order, 0);
    assert_eq!(report.totals.received, 4 * report.published);
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rtt_one_in_flight_and_at_a_rate() {
    let (handle, url) = broker().await;
    let dir = scratch_dir("rtt");
    for rate in [0.0, 500.0] {
        let args = rtt::RttArgs {
            url: url.clone(),
            sizes: vec![8, 16, 128],
            count: 30,
            warmup: 5,
            rate,
            svg: Some(dir.join("rtt.svg")),
            json: Some(dir.join("rtt.json")),
            quiet: true,
            ..Default::default()
        };
        let report = rtt::run(&args).await.unwrap();
        assert_eq!(report.sizes.len(), 3);
        for size in &report.sizes {
            assert_eq!(size.lost, 0);
            assert_eq!(size.stats.count, 30);
            assert!(size.stats.min_us <= size.stats.median_us);
            assert!(size.stats.median_us <= size.stats.max_us);
        }
    }
    let svg = std::fs::read_to_string(dir.join("rtt.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("128 B"));
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quality_loses_nothing() {
    let (handle, url) = broker().await;
    let args = quality::QualityArgs {
        url,
        count: 2000,
        rate: 0.0,
        repeat: 2,
        quiet: true,
        ..Default::default()
    };
    let report = quality::run(&args).await.unwrap();
    assert!(report.drained);
    assert_eq!(report.delivered, 4 * 2 * 2000);
    assert_eq!(report.lost, 0);
    assert_eq!(report.order_errors, 0);
    assert_eq!(report.duplicates, 0);
    assert_eq!(report.rows.len(), 8);
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn memory_of_an_in_process_broker() {
    let (handle, url) = broker().await;
    let args = memory::MemoryArgs {
        url,
        pid: Some(std::process::id()),
        connections: 20,
        backlog: 5000,
        settle: 0.0,
        quiet: true,
        ..Default::default()
    };
    let report = memory::run(&args).await.unwrap();
    assert!(report.idle_bytes > 0);
    assert_eq!(report.connections.unwrap().connections, 20);
    assert_eq!(report.backlog.unwrap().messages, 5000);
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compare_three_brokers_with_an_external_generator() {
    let (a, url_a) = broker().await;
    let (b, url_b) = broker().await;
    let (c, url_c) = broker().await;
    let dir = scratch_dir("compare");
    let me = std::process::id();
    // An "external generator" that reports fixed rates, and proves it was
    // given each broker's URL by echoing it to a file.
    let seen = dir.join("seen-urls");
    let external = format!(
        "fake=echo {{url}} {{queue}} >> {} && echo 'progress line' && \
         echo '{{\"elapsed_seconds\":2,\"avg_pub_rate\":1000,\"avg_consume_rate\":900}}'",
        seen.display()
    );
    let args = compare::CompareArgs {
        urls: vec![url_a.clone(), url_b.clone(), url_c.clone()],
        names: ["a", "b", "c"].map(String::from).to_vec(),
        pids: vec![me, me, me],
        externals: vec![external],
        duration: 0.3,
        warmup: 0.0,
        rtt_count: 20,
        rtt_warmup: 2,
        memory_connections: Some(5),
        memory_backlog: Some(1000),
        quality: Some(200),
        quality_rate: 0.0,
        only: [
            "noack", "confirm", "fanout", "rtt16", "idle", "conns", "backlog", "quality", "fake",
        ]
        .map(String::from)
        .to_vec(),
        settle: 0.0,
        json: Some(dir.join("compare.json")),
        svg: Some(dir.join("compare.svg")),
        ..Default::default()
    };
    let report = compare::run(&args).await.unwrap();
    for scenario in [
        "noack", "confirm", "fanout", "rtt16", "idle", "conns", "backlog", "quality", "fake",
    ] {
        let rows: Vec<_> = report
            .figures
            .iter()
            .filter(|f| f.scenario == scenario)
            .collect();
        assert!(!rows.is_empty(), "{scenario}");
        assert!(
            rows.iter()
                .all(|f| f.values.len() == 3 && f.values.iter().all(Option::is_some)),
            "{scenario}"
        );
        assert!(rows.iter().all(|f| f.ratios.len() == 2), "{scenario}");
    }
    let lost: Vec<_> = report
        .figures
        .iter()
        .filter(|f| f.figure == "lost")
        .collect();
    assert!(lost
        .iter()
        .all(|f| f.values.iter().all(|v| *v == Some(0.0))));
    // The external generator ran once per broker, with its URL, and its
    // JSON line gave the rates; the broker's CPU per message is beside them.
    let fake = |figure: &str| {
        report
            .figures
            .iter()
            .find(|f| f.scenario == "fake" && f.figure == figure)
            .unwrap_or_else(|| panic!("no {figure} row"))
    };
    assert_eq!(fake("consume rate").values, vec![Some(900.0); 3]);
    assert_eq!(fake("publish rate").ratios, vec![Some(1.0); 2]);
    assert!(fake("broker CPU per message")
        .values
        .iter()
        .all(Option::is_some));
    // Each run had a queue name of its own.
    let seen = std::fs::read_to_string(&seen).unwrap();
    let seen: Vec<(&str, &str)> = seen.lines().filter_map(|l| l.split_once(' ')).collect();
    let urls: Vec<&str> = seen.iter().map(|(url, _)| *url).collect();
    assert_eq!(urls, [&url_a, &url_b, &url_c]);
    let queues: std::collections::HashSet<&str> = seen.iter().map(|(_, q)| *q).collect();
    assert_eq!(queues.len(), 3, "{seen:?}");
    assert!(report
        .figures
        .iter()
        .any(|f| f.scenario == "noack" && f.figure == "broker CPU per message"));
    assert!(dir.join("compare.json").exists());
    let svg = std::fs::read_to_string(dir.join("compare.svg")).unwrap();
    assert!(svg.contains("round trip, 16 B"));
    a.shutdown().await;
    b.shutdown().await;
    c.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ports_round_trips_every_carrier_and_skips_an_absent_rabbitmq() {
    let dir = scratch_dir("ports");
    let json = dir.join("ports.json");
    let dump = dir.join("samples");
    let cli = Cli::try_parse_from([
        "leveret-perf",
        "ports",
        "--transports",
        "in-process,leveret-tcp,rabbitmq",
        // Nothing listens on port 1: RabbitMQ's rows are skipped.
        "--rabbit-url",
        "amqp://guest:guest@127.0.0.1:1/%2f",
        "--sizes",
        "8,128",
        "--paced-count",
        "5",
        "--paced-warmup",
        "1",
        "--unthrottled-count",
        "20",
        "--unthrottled-warmup",
        "5",
        "--paced-extras",
        "--quiet",
        "--json",
        json.to_str().unwrap(),
        "--dump",
        dump.to_str().unwrap(),
    ])
    .unwrap();
    let Command::Ports(args) = cli.command else {
        panic!("the ports subcommand");
    };
    let report = ports::run(&args).await.unwrap();
    assert_eq!(report.skipped, [ports::Transport::RabbitMq]);
    // 2 modes x (2 sizes + confirmed ports + raw client) x 2 transports
    // round trips, and a one-way row for each of the 12 carried by ports.
    let round_trips = report
        .rows
        .iter()
        .filter(|r| r.leg == ports::Leg::RoundTrip)
        .count();
    assert_eq!(round_trips, 16);
    let one_way: Vec<_> = report
        .rows
        .iter()
        .filter(|r| r.leg == ports::Leg::OneWay)
        .collect();
    assert_eq!(one_way.len(), 12);
    assert!(one_way
        .iter()
        .all(|r| r.carrier != ports::Carrier::RawClient));
    for row in &report.rows {
        assert_eq!(row.lost, 0, "{row:?}");
        let expected = match row.mode {
            ports::Mode::Paced => 5,
            ports::Mode::Unthrottled => 20,
        };
        assert_eq!(row.stats.count, expected, "{row:?}");
        assert!(row.stats.min_us > 0.0 && row.stats.min_us <= row.stats.max_us);
    }
    assert_eq!(report.echo_failures, 0);
    let text = std::fs::read_to_string(&json).unwrap();
    assert!(text.contains("\"carrier\": \"raw-client\""), "{text}");
    // Samples are dumped per round-trip row.
    assert_eq!(std::fs::read_dir(&dump).unwrap().count(), 16);
    let _ = std::fs::remove_dir_all(&dir);
}
