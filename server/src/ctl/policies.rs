//! The policy commands, with rabbitmqctl's syntax: `set_policy [-p
//! VHOST] [--priority N] [--apply-to X] NAME PATTERN DEFINITION`,
//! `clear_policy`, `list_policies`, their `operator_policy` siblings,
//! `set_cluster_name` and `set_global_parameter NAME VALUE`,
//! `clear_global_parameter`, `list_global_parameters`; over
//! `/api/policies`, `/api/operator-policies`, `/api/cluster-name` and
//! `/api/global-parameters`.

use super::{columns, info, print_table, Cli, Failure};
use crate::client::{segment, Client};
use clap::Subcommand;
use serde_json::{json, Value};

#[derive(Debug, Subcommand)]
#[command(rename_all = "snake_case")]
pub enum PolicyCommand {
    /// Sets a policy on the vhost (DEFINITION is a JSON object).
    SetPolicy(SetPolicy),
    /// Clears a policy of the vhost.
    ClearPolicy { name: String },
    /// Lists the vhost's policies: vhost, name, pattern, apply-to,
    /// definition, priority.
    ListPolicies,
    /// Sets an operator policy on the vhost (keys: expires, message-ttl,
    /// max-length, max-length-bytes).
    SetOperatorPolicy(SetPolicy),
    /// Clears an operator policy of the vhost.
    ClearOperatorPolicy { name: String },
    /// Lists the vhost's operator policies.
    ListOperatorPolicies,
    /// Sets the cluster name (shown by /api/overview and exported).
    SetClusterName { name: String },
    /// Sets a global runtime parameter (VALUE is JSON): cluster_name,
    /// mqtt_port_to_vhost_mapping or mqtt_default_vhosts.
    SetGlobalParameter { name: String, value: String },
    /// Clears a global runtime parameter.
    ClearGlobalParameter { name: String },
    /// Lists the global runtime parameters: name, value.
    ListGlobalParameters,
}

#[derive(Debug, clap::Args)]
pub struct SetPolicy {
    name: String,
    /// A regular expression on queue or exchange names.
    pattern: String,
    /// The policy's keys, as a JSON object.
    definition: String,
    /// Higher wins when several policies match.
    #[arg(long, default_value_t = 0)]
    priority: i64,
    /// queues, exchanges or all.
    #[arg(long = "apply-to", default_value = "all")]
    apply_to: String,
}

fn path(kind: &str, vhost: &str, name: Option<&str>) -> String {
    match name {
        Some(name) => format!("/api/{kind}/{}/{}", segment(vhost), segment(name)),
        None => format!("/api/{kind}/{}", segment(vhost)),
    }
}

/// Runs one policy command.
pub fn run(cli: &Cli, client: &Client, command: &PolicyCommand) -> Result<(), Failure> {
    let vhost = cli.vhost.as_str();
    let set = |kind: &str, what: &str, p: &SetPolicy| -> Result<(), Failure> {
        let definition: Value = serde_json::from_str(&p.definition)
            .map_err(|e| Failure::Usage(format!("the definition is not JSON: {e}")))?;
        info(
            cli,
            &format!("Setting {what} \"{}\" for pattern \"{}\" to \"{}\" with priority \"{}\" for vhost \"{vhost}\" ...",
                p.name, p.pattern, p.definition, p.priority),
        )?;
        let body = json!({"pattern": p.pattern, "definition": definition,
                          "priority": p.priority, "apply-to": p.apply_to});
        client.put(
            &path(kind, vhost, Some(&p.name)),
            body.to_string().as_bytes(),
        )?;
        Ok(())
    };
    let clear = |kind: &str, what: &str, name: &str| -> Result<(), Failure> {
        info(
            cli,
            &format!("Clearing {what} \"{name}\" on vhost \"{vhost}\" ..."),
        )?;
        client.delete(&path(kind, vhost, Some(name)), &[])?;
        Ok(())
    };
    let list = |kind: &str, what: &str| -> Result<(), Failure> {
        info(cli, &format!("Listing {what} for vhost \"{vhost}\" ..."))?;
        let listed = client.get(&path(kind, vhost, None))?;
        print_table(cli, &columns::POLICIES, &[], &listed)
    };
    match command {
        PolicyCommand::SetPolicy(p) => set("policies", "policy", p),
        PolicyCommand::ClearPolicy { name } => clear("policies", "policy", name),
        PolicyCommand::ListPolicies => list("policies", "policies"),
        PolicyCommand::SetOperatorPolicy(p) => set("operator-policies", "operator policy", p),
        PolicyCommand::ClearOperatorPolicy { name } => {
            clear("operator-policies", "operator policy", name)
        }
        PolicyCommand::ListOperatorPolicies => list("operator-policies", "operator policies"),
        PolicyCommand::SetClusterName { name } => {
            info(cli, &format!("Setting cluster name to {name} ..."))?;
            client.put(
                "/api/cluster-name",
                json!({"name": name}).to_string().as_bytes(),
            )?;
            Ok(())
        }
        PolicyCommand::SetGlobalParameter { name, value } => {
            let parsed: Value = serde_json::from_str(value)
                .map_err(|e| Failure::Usage(format!("the value is not JSON: {e}")))?;
            info(
                cli,
                &format!("Setting global runtime parameter \"{name}\" to \"{value}\" ..."),
            )?;
            let body = json!({"name": name, "value": parsed});
            client.put(&global(name), body.to_string().as_bytes())?;
            Ok(())
        }
        PolicyCommand::ClearGlobalParameter { name } => {
            info(
                cli,
                &format!("Clearing global runtime parameter \"{name}\" ..."),
            )?;
            client.delete(&global(name), &[])?;
            Ok(())
        }
        PolicyCommand::ListGlobalParameters => {
            info(cli, "Listing global runtime parameters ...")?;
            let listed = client.get("/api/global-parameters")?;
            print_table(cli, &columns::GLOBAL_PARAMETERS, &[], &listed)
        }
    }
}

fn global(name: &str) -> String {
    format!("/api/global-parameters/{}", segment(name))
}
