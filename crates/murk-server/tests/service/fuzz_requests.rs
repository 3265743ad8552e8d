//! A mutation fuzzer for the request decoders and validation, on stable Rust with proptest.
//!
//! The corpus (`tests/fuzz-corpus/*.pb`, written by `cargo run -p murk-server --example
//! fuzz_corpus`) holds one small valid `JobRequest` per method. Each case takes a seed and
//! applies a few byte-level mutations that a broken or hostile client produces: bit flips,
//! overwritten bytes, extreme varints and floats spliced in, truncation, insertion and
//! duplication. The result goes through the server's decode-and-validate path
//! (`rebuild_work`, the same that SubmitJob and a journal restart use), which must answer
//! `Ok` or an error, never panic, and name a field in every INVALID_ARGUMENT.
//!
//! The case count and the RNG seed are fixed, so CI runs the same bounded search every time;
//! failures are kept in `proptest-regressions/` and replayed first. A longer search:
//! `PROPTEST_CASES=100000 cargo test --release -p murk-server --test service fuzz_requests`.

use std::path::PathBuf;
use std::sync::LazyLock;

use murk::params::airlight::AirlightEstimator;
use murk::MurkError;
use murk_server::service::convert::{AirlightService, ImageLimits};
use murk_server::service::{rebuild_work, RequestLimits};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};

/// Cases per run, over all seeds: about a second in release. About 80 % of mutants no longer
/// decode (a shifted length), 14 % validate and 5 % are refused naming a field.
const CASES: u32 = 3000;

fn corpus_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-corpus")
}

/// The corpus, sorted by file name so the search is the same on every machine.
fn corpus() -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<_> = std::fs::read_dir(corpus_dir())
        .expect("tests/fuzz-corpus exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "pb"))
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect()
}

/// Small images keep accepted mutants cheap to decode; the bound is what matters, not its size.
fn limits() -> RequestLimits {
    RequestLimits {
        images: ImageLimits {
            max_pixels: 1 << 16,
            max_channels: 4,
        },
        max_ps_kernel_bytes: 64 << 20,
    }
}

/// One byte-level edit; positions are fractions of the current length, so every edit applies
/// to any seed.
#[derive(Clone, Debug)]
enum Mutation {
    FlipBit {
        at: f64,
        bit: u8,
    },
    SetByte {
        at: f64,
        value: u8,
    },
    /// Overwrites with an extreme little-endian f32 or f64, or a maximal varint.
    Splice {
        at: f64,
        which: usize,
    },
    Truncate {
        at: f64,
    },
    Insert {
        at: f64,
        bytes: Vec<u8>,
    },
    Duplicate {
        at: f64,
        len: usize,
    },
}

const SPLICES: &[&[u8]] = &[
    &[0xff, 0xff, 0x7f, 0x7f],                                     // f32::MAX
    &[0x01, 0x00, 0x00, 0x00],                                     // the smallest f32 subnormal
    &[0x00, 0x00, 0xc0, 0x7f],                                     // f32 NaN
    &[0x00, 0x00, 0x80, 0xff],                                     // f32 −inf
    &[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xef, 0x7f],             // f64::MAX
    &[0x01, 0, 0, 0, 0, 0, 0, 0],                                  // the smallest f64 subnormal
    &[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01], // u64::MAX as a varint
    &[0x80, 0x80, 0x80, 0x80, 0x08],                               // 2^31 as a varint
];

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = 0.0f64..1.0;
    prop_oneof![
        (at.clone(), 0u8..8).prop_map(|(at, bit)| Mutation::FlipBit { at, bit }),
        (at.clone(), any::<u8>()).prop_map(|(at, value)| Mutation::SetByte { at, value }),
        (at.clone(), 0..SPLICES.len()).prop_map(|(at, which)| Mutation::Splice { at, which }),
        at.clone().prop_map(|at| Mutation::Truncate { at }),
        (at.clone(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        (at, 1usize..64).prop_map(|(at, len)| Mutation::Duplicate { at, len }),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    let pos = |at: f64, len: usize| ((at * len as f64) as usize).min(len.saturating_sub(1));
    let n = bytes.len();
    if n == 0 {
        return;
    }
    match m {
        Mutation::FlipBit { at, bit } => bytes[pos(*at, n)] ^= 1 << bit,
        Mutation::SetByte { at, value } => bytes[pos(*at, n)] = *value,
        Mutation::Splice { at, which } => {
            let s = SPLICES[*which];
            let start = pos(*at, n);
            for (i, b) in s.iter().enumerate() {
                if let Some(slot) = bytes.get_mut(start + i) {
                    *slot = *b;
                }
            }
        }
        Mutation::Truncate { at } => bytes.truncate(pos(*at, n)),
        Mutation::Insert { at, bytes: new } => {
            let at = pos(*at, n);
            bytes.splice(at..at, new.iter().copied());
        }
        Mutation::Duplicate { at, len } => {
            let start = pos(*at, n);
            let end = (start + len).min(n);
            let copy = bytes[start..end].to_vec();
            bytes.splice(end..end, copy);
        }
    }
}

/// The rules every answer keeps.
fn check(bytes: &[u8], airlight: &AirlightService) -> Result<(), TestCaseError> {
    match rebuild_work(bytes, &limits(), airlight) {
        Ok(_) => Ok(()),
        Err(
            MurkError::InvalidArgument { field, reason } | MurkError::OverLimit { field, reason },
        ) => {
            prop_assert!(!field.is_empty(), "an error without a field: {reason}");
            prop_assert!(field.len() < 200, "a field name of {} bytes", field.len());
            Ok(())
        }
        // Bytes that are not a JobRequest (the API answers these INVALID_ARGUMENT itself).
        Err(MurkError::Internal(m)) if m.contains("does not decode") => Ok(()),
        Err(other) => Err(TestCaseError::fail(format!("{other:?}"))),
    }
}

fn airlight() -> AirlightService {
    AirlightService::new(AirlightEstimator::DarkChannel(Default::default()))
}

static SEEDS: LazyLock<Vec<(String, Vec<u8>)>> = LazyLock::new(corpus);

#[test]
fn every_corpus_seed_is_a_valid_request() {
    assert!(
        SEEDS.len() >= 5,
        "one seed per method, found {}",
        SEEDS.len()
    );
    for (name, bytes) in SEEDS.iter() {
        if let Err(e) = rebuild_work(bytes, &limits(), &airlight()) {
            panic!(
                "{name}: the seed no longer validates ({e}); rewrite the corpus with \
                 `cargo run -p murk-server --example fuzz_corpus`"
            );
        }
    }
}

proptest! {
    #![proptest_config(Config {
        // `PROPTEST_CASES` runs a longer search.
        cases: std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(CASES),
        rng_seed: RngSeed::Fixed(0x6d75_726b),
        ..Config::default()
    })]

    #[test]
    fn mutated_requests_are_answered_without_a_panic_and_errors_name_a_field(
        seed in any::<prop::sample::Index>(),
        mutations in prop::collection::vec(mutation(), 1..6),
    ) {
        let mut bytes = seed.get(&SEEDS).1.clone();
        for m in &mutations {
            apply(&mut bytes, m);
        }
        check(&bytes, &airlight())?;
    }
}
