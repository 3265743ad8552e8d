//! The protos' conventions, checked on the descriptors the server is built from: what buf's
//! `DEFAULT` lint category asks of names and enums, and what client authors in Go and Java need
//! from the file options. (buf itself is not among the build's dependencies.)
//!
//! Enforced: package `murk.v1` in `murk/v1/`; `go_package` a module import path with the
//! package name `murkv1`; `java_package`; PascalCase messages, enums, services and RPCs;
//! lower_snake_case fields and oneofs; UPPER_SNAKE enum values prefixed with their enum's name;
//! every enum's zero value `…_UNSPECIFIED`. Not enforced: buf's one-request-and-response-message
//! per RPC rule (`SubmitJob` answers a `Job`, as `GetJob` does).

use murk_server::service::proto::FILE_DESCRIPTOR_SET;
use prost_reflect::{DescriptorPool, EnumDescriptor, MessageDescriptor};

fn is_pascal(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_uppercase())
        && name.chars().all(|c| c.is_ascii_alphanumeric())
}

fn is_lower_snake(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
        && !name.contains("__")
}

fn is_upper_snake(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_uppercase())
        && name
            .chars()
            .all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_')
        && !name.contains("__")
}

/// `TransferFunction` → `TRANSFER_FUNCTION`.
fn upper_snake_of(pascal: &str) -> String {
    let mut out = String::new();
    for (i, c) in pascal.chars().enumerate() {
        if c.is_ascii_uppercase() && i > 0 {
            out.push('_');
        }
        out.push(c.to_ascii_uppercase());
    }
    out
}

fn check_enum(e: &EnumDescriptor, problems: &mut Vec<String>) {
    let name = e.full_name();
    if !is_pascal(e.name()) {
        problems.push(format!("enum {name}: not PascalCase"));
    }
    let prefix = format!("{}_", upper_snake_of(e.name()));
    for v in e.values() {
        if !is_upper_snake(v.name()) || !v.name().starts_with(&prefix) {
            problems.push(format!(
                "enum {name}: value {} is not UPPER_SNAKE with the prefix {prefix}",
                v.name()
            ));
        }
    }
    match e.get_value(0) {
        Some(zero) if zero.name() == format!("{prefix}UNSPECIFIED") => {}
        Some(zero) => problems.push(format!(
            "enum {name}: its zero value is {}, not {prefix}UNSPECIFIED",
            zero.name()
        )),
        None => problems.push(format!("enum {name}: no zero value")),
    }
}

fn check_message(m: &MessageDescriptor, problems: &mut Vec<String>) {
    let name = m.full_name();
    if !is_pascal(m.name()) {
        problems.push(format!("message {name}: not PascalCase"));
    }
    for f in m.fields() {
        if !is_lower_snake(f.name()) {
            problems.push(format!("{name}.{}: not lower_snake_case", f.name()));
        }
    }
    // The synthetic oneofs of proto3 `optional` fields are named `_field` by protoc.
    for o in m.oneofs().filter(|o| !o.is_synthetic()) {
        if !is_lower_snake(o.name()) {
            problems.push(format!("{name} oneof {}: not lower_snake_case", o.name()));
        }
    }
    for e in m.child_enums() {
        check_enum(&e, problems);
    }
    for child in m.child_messages() {
        // Map entries are generated, not written.
        if !child.is_map_entry() {
            check_message(&child, problems);
        }
    }
}

#[test]
fn the_protos_follow_the_lint_conventions() {
    let pool = DescriptorPool::decode(FILE_DESCRIPTOR_SET).expect("descriptors");
    let mut problems = Vec::new();
    let mut files = 0;
    for file in pool.files().filter(|f| f.package_name() == "murk.v1") {
        files += 1;
        let path = file.name();
        if !path.starts_with("murk/v1/") {
            problems.push(format!("{path}: not under murk/v1/"));
        }
        let options = &file.file_descriptor_proto().options;
        let go = options.as_ref().and_then(|o| o.go_package.clone());
        match go.as_deref().and_then(|g| g.split_once(';')) {
            Some((import, "murkv1"))
                if import
                    .split('/')
                    .next()
                    .is_some_and(|host| host.contains('.')) => {}
            _ => problems.push(format!(
                "{path}: go_package {go:?} is not `DOMAIN/PATH;murkv1` (a module import path)"
            )),
        }
        if options
            .as_ref()
            .and_then(|o| o.java_package.clone())
            .is_none()
        {
            problems.push(format!("{path}: no java_package"));
        }
        for e in file.enums() {
            check_enum(&e, &mut problems);
        }
        for m in file.messages() {
            check_message(&m, &mut problems);
        }
        for s in file.services() {
            if !is_pascal(s.name()) {
                problems.push(format!("service {}: not PascalCase", s.full_name()));
            }
            for rpc in s.methods() {
                if !is_pascal(rpc.name()) {
                    problems.push(format!("rpc {}: not PascalCase", rpc.full_name()));
                }
            }
        }
    }
    assert!(files >= 8, "found {files} murk.v1 files");
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_checks_catch_what_they_look_for() {
    assert_eq!(upper_snake_of("BetaBound"), "BETA_BOUND");
    assert!(is_lower_snake("beta_per_mm") && !is_lower_snake("betaPerMm"));
    assert!(is_upper_snake("BETA_BOUND_MIN") && !is_upper_snake("Beta_MIN"));
    assert!(is_pascal("JobRequest") && !is_pascal("job_request"));
}
