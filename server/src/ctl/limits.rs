//! The limit commands, as rabbitmqctl's: `set_vhost_limits -p VHOST
//! '{"max-connections": 10}'` (the definition replaces the vhost's
//! limits), `clear_vhost_limits`, `list_vhost_limits [--global]`,
//! `set_user_limits USER '{"max-channels": 5}'` (added to the user's
//! limits), `clear_user_limits USER NAME|all`, `list_user_limits [--user
//! USER | --global]`. Limits print as rabbitmqctl prints them: a compact
//! JSON object with sorted keys, and with `--global` a `vhost`/`user` and
//! `limits` table. Definitions are checked here first, with RabbitMQ's
//! names, so that a bad one changes nothing.

use super::{info, segment, Cli, Client, Failure, Formatter};
use leveret_broker::{UserLimits, VhostLimits};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::io::Write;

/// What a limits command asks.
#[derive(Debug)]
pub enum LimitsCommand<'a> {
    SetVhost(&'a str),
    ClearVhost,
    ListVhost { global: bool },
    SetUser(&'a str, &'a str),
    ClearUser(&'a str, &'a str),
    ListUser { user: &'a str, global: bool },
}

/// A definition's limits by name, each known to `check` (RabbitMQ's
/// "Unrecognised terms" otherwise).
fn definition(
    text: &str,
    check: impl Fn(&str, i64) -> bool,
    kind: &str,
) -> Result<BTreeMap<String, i64>, Failure> {
    let parsed: Value = serde_json::from_str(text)
        .map_err(|e| Failure::Usage(format!("the definition is not JSON: {e}")))?;
    let object = parsed
        .as_object()
        .ok_or_else(|| Failure::Usage("the definition must be a JSON object".into()))?;
    let mut limits = BTreeMap::new();
    for (name, value) in object {
        match value.as_i64() {
            Some(value) if check(name, value) => {
                limits.insert(name.clone(), value);
            }
            _ => {
                return Err(Failure::Usage(format!(
                    "Validation failed\n\nUnrecognised terms [{{{name},{value}}}] in {kind}"
                )))
            }
        }
    }
    Ok(limits)
}

/// `{"max-connections":10}` with sorted keys, as rabbitmqctl prints it.
fn compact(value: &Value) -> String {
    let sorted: BTreeMap<&String, &Value> = value.as_object().into_iter().flatten().collect();
    serde_json::to_string(&sorted).unwrap_or_default()
}

fn print(cli: &Cli, key: &str, listed: &Value, global: bool) -> Result<(), Failure> {
    let entries = listed.as_array().cloned().unwrap_or_default();
    let mut out = std::io::stdout().lock();
    if !global {
        let limits = entries.first().map_or(json!({}), |e| e["value"].clone());
        match cli.formatter {
            Formatter::Table => writeln!(out, "{}", compact(&limits))?,
            Formatter::Json => writeln!(out, "{limits}")?,
        }
        return Ok(());
    }
    match cli.formatter {
        Formatter::Table => {
            if !cli.no_table_headers {
                writeln!(out, "{key}\tlimits")?;
            }
            for entry in &entries {
                let name = entry[key].as_str().unwrap_or_default();
                writeln!(out, "{name}\t{}", compact(&entry["value"]))?;
            }
        }
        Formatter::Json => {
            let rows: Vec<Value> = (entries.iter())
                .map(|e| json!({key: e[key], "limits": e["value"]}))
                .collect();
            writeln!(out, "{}", Value::Array(rows))?;
        }
    }
    Ok(())
}

pub fn run(cli: &Cli, client: &Client, command: LimitsCommand<'_>) -> Result<(), Failure> {
    let vhost = segment(&cli.vhost);
    let put = |path: String, value: i64| {
        client.put(&path, json!({ "value": value }).to_string().as_bytes())
    };
    match command {
        LimitsCommand::SetVhost(text) => {
            info(
                cli,
                &format!(
                    "Setting vhost limits to \"{text}\" for vhost \"{}\" ...",
                    cli.vhost
                ),
            )?;
            let check = |name: &str, value| VhostLimits::default().with(name, value).is_ok();
            let limits = definition(text, check, "limits")?;
            // The definition replaces the vhost's limits.
            for name in ["max-connections", "max-queues"] {
                let path = format!("/api/vhost-limits/{vhost}/{name}");
                match limits.get(name) {
                    Some(value) => put(path, *value)?,
                    None => client.delete(&path, &[])?,
                };
            }
        }
        LimitsCommand::ClearVhost => {
            info(cli, &format!("Clearing vhost \"{}\" limits ...", cli.vhost))?;
            for name in ["max-connections", "max-queues"] {
                client.delete(&format!("/api/vhost-limits/{vhost}/{name}"), &[])?;
            }
        }
        LimitsCommand::ListVhost { global: true } => {
            info(cli, "Listing limits for all vhosts ...")?;
            print(cli, "vhost", &client.get("/api/vhost-limits")?, true)?;
        }
        LimitsCommand::ListVhost { global: false } => {
            info(
                cli,
                &format!("Listing limits for vhost \"{}\" ...", cli.vhost),
            )?;
            let listed = client.get(&format!("/api/vhost-limits/{vhost}"))?;
            print(cli, "vhost", &listed, false)?;
        }
        LimitsCommand::SetUser(user, text) => {
            info(
                cli,
                &format!("Setting user limits to \"{text}\" for user \"{user}\" ..."),
            )?;
            let check = |name: &str, value| UserLimits::default().with(name, value).is_ok();
            for (name, value) in definition(text, check, "user-limits")? {
                put(format!("/api/user-limits/{}/{name}", segment(user)), value)?;
            }
        }
        LimitsCommand::ClearUser(user, "all") => {
            info(cli, &format!("Clearing all limits for user \"{user}\" ..."))?;
            for name in ["max-connections", "max-channels"] {
                client.delete(&format!("/api/user-limits/{}/{name}", segment(user)), &[])?;
            }
        }
        LimitsCommand::ClearUser(user, name) => {
            info(
                cli,
                &format!("Clearing \"{name}\" limit for user \"{user}\" ..."),
            )?;
            client.delete(&format!("/api/user-limits/{}/{name}", segment(user)), &[])?;
        }
        LimitsCommand::ListUser { global: true, .. } => {
            info(cli, "Listing limits for all users ...")?;
            print(cli, "user", &client.get("/api/user-limits")?, true)?;
        }
        LimitsCommand::ListUser { user, .. } => {
            info(cli, &format!("Listing limits for user \"{user}\" ..."))?;
            let listed = client.get(&format!("/api/user-limits/{}", segment(user)))?;
            print(cli, "user", &listed, false)?;
        }
    }
    Ok(())
}
