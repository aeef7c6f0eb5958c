//! `#[both_runtimes]`: an async test that runs twice, once on a
//! current-thread tokio runtime and once on a multi-thread one with
//! `WORKERS` workers, so a race that one thread's scheduling hides shows
//! up in the same `cargo test` run.
//!
//! ```ignore
//! #[both_runtimes]
//! async fn prefetch_limits_unacked_deliveries() { /* … */ }
//! ```
//!
//! keeps the function as written and adds a module of the same name with
//! two `#[tokio::test]`s calling it, so the test names say the runtime:
//! `prefetch_limits_unacked_deliveries::current_thread` and
//! `prefetch_limits_unacked_deliveries::multi_thread` (`cargo test
//! multi_thread` runs one flavour). `#[ignore]` and `#[should_panic]` on
//! the function move to both tests. Whatever the test starts (an embedded
//! broker, clients) runs on the test's runtime, as in an embedding
//! application.
//!
//! The crate uses only `proc_macro`: the item is read as tokens, never
//! parsed into a syntax tree.
#![forbid(unsafe_code)]

use proc_macro::{Delimiter, TokenStream, TokenTree};

/// Worker threads of the multi-thread variant.
const WORKERS: usize = 4;

/// Runs the async test fn it is put on as two tests, on a current-thread and
/// on a multi-thread runtime (see the crate docs).
#[proc_macro_attribute]
pub fn both_runtimes(args: TokenStream, item: TokenStream) -> TokenStream {
    if !args.is_empty() {
        return compile_error("#[both_runtimes] takes no arguments");
    }
    match expand(item) {
        Ok(tokens) => tokens,
        Err(message) => compile_error(message),
    }
}

/// The function with its test attributes moved, and the two tests.
fn expand(item: TokenStream) -> Result<TokenStream, &'static str> {
    let tokens: Vec<TokenTree> = item.into_iter().collect();
    let mut kept: Vec<TokenTree> = Vec::with_capacity(tokens.len());
    let mut test_attributes = String::new();
    let mut index = 0;
    // Outer attributes: `#` then a bracketed group.
    while let (Some(TokenTree::Punct(hash)), Some(TokenTree::Group(group))) =
        (tokens.get(index), tokens.get(index + 1))
    {
        if hash.as_char() != '#' || group.delimiter() != Delimiter::Bracket {
            break;
        }
        let first = group.stream().into_iter().next();
        if matches!(&first, Some(TokenTree::Ident(i)) if is_test_attribute(&i.to_string())) {
            test_attributes.push_str(&format!("#{group} "));
        } else {
            kept.extend([tokens[index].clone(), tokens[index + 1].clone()]);
        }
        index += 2;
    }
    let signature = &tokens[index..];
    let fn_at = signature
        .iter()
        .position(|t| matches!(t, TokenTree::Ident(i) if i.to_string() == "fn"))
        .ok_or("#[both_runtimes] goes on an async fn")?;
    let is_async = signature[..fn_at]
        .iter()
        .any(|t| matches!(t, TokenTree::Ident(i) if i.to_string() == "async"));
    if !is_async {
        return Err("#[both_runtimes] goes on an async fn");
    }
    let Some(TokenTree::Ident(name)) = signature.get(fn_at + 1) else {
        return Err("#[both_runtimes]: expected the function's name after `fn`");
    };
    let Some(TokenTree::Group(params)) = signature.get(fn_at + 2) else {
        return Err("#[both_runtimes]: a test function takes no generics");
    };
    if params.delimiter() != Delimiter::Parenthesis || !params.stream().is_empty() {
        return Err("#[both_runtimes]: a test function takes no arguments");
    }
    // Between the parameters and the body: `-> Type`, if any.
    let body_at = signature.len() - 1;
    if !matches!(&signature[body_at], TokenTree::Group(g) if g.delimiter() == Delimiter::Brace) {
        return Err("#[both_runtimes]: expected the function's body");
    }
    let output: TokenStream = signature[fn_at + 3..body_at].iter().cloned().collect();
    kept.extend(signature.iter().cloned());

    let tests = format!(
        "mod {name} {{
            #[::tokio::test(flavor = \"current_thread\")]
            {test_attributes}
            async fn current_thread() {output} {{ super::{name}().await }}

            #[::tokio::test(flavor = \"multi_thread\", worker_threads = {WORKERS})]
            {test_attributes}
            async fn multi_thread() {output} {{ super::{name}().await }}
        }}"
    );
    let mut expanded: TokenStream = kept.into_iter().collect();
    expanded.extend(
        tests
            .parse::<TokenStream>()
            .map_err(|_| "#[both_runtimes]: bad return type")?,
    );
    Ok(expanded)
}

/// Attributes that belong on the generated tests, not on the function.
fn is_test_attribute(name: &str) -> bool {
    matches!(name, "ignore" | "should_panic")
}

fn compile_error(message: &str) -> TokenStream {
    format!("::core::compile_error!({message:?});")
        .parse()
        .expect("a compile_error! invocation parses")
}
