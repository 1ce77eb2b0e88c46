//! The unpickler against pickles written by numpy (`scripts/make_phystwin_fixture.py`,
//! committed under `fixtures/`), hostile hand-made pickles, and a deterministic
//! mutation fuzzer.

use std::path::{Path, PathBuf};

use dm_numpy::pickle::{Limits, Value, from_slice, from_slice_with_limits};
use dm_numpy::{ArrayData, Element, NdArray};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn read(relative: &str) -> Vec<u8> {
    let path = fixtures().join(relative);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

const DTYPES: [(&str, Element); 11] = [
    ("f4", Element::F32),
    ("f8", Element::F64),
    ("i4", Element::I32),
    ("i8", Element::I64),
    ("u1", Element::U8),
    ("u2", Element::U16),
    ("b1", Element::Bool),
    ("i2", Element::I16),
    ("u4", Element::U32),
    ("u8", Element::U64),
    ("i1", Element::I8),
];

/// The script's `typed_array(code, shape)`, as f64 (bools as 0/1), C order.
fn typed_values(code: &str, count: usize) -> Vec<f64> {
    (0..count)
        .map(|v| {
            let v = v as f64;
            match &code[..1] {
                "b" => f64::from(u8::from((v as usize).is_multiple_of(3))),
                "f" => v * 0.5 - 3.0,
                "i" => v - 5.0,
                _ => v,
            }
        })
        .collect()
}

fn numeric(array: &NdArray) -> Vec<f64> {
    match array.as_bools() {
        Some(bools) => bools.iter().map(|&b| f64::from(u8::from(b))).collect(),
        None => array.to_f64_vec().expect("numeric"),
    }
}

fn array<'a>(root: &'a Value, key: &str) -> &'a NdArray {
    match root.get(key) {
        Some(Value::Array(a)) => a,
        other => panic!("{key}: expected an array, found {other:?}"),
    }
}

fn check_payload(name: &str) {
    let root = from_slice(&read(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    for (code, element) in DTYPES {
        for order in ["c", "f"] {
            let a = array(&root, &format!("{code}_{order}"));
            assert_eq!(a.element(), element, "{name} {code}_{order}");
            assert_eq!(a.shape(), [2, 3, 4], "{name} {code}_{order}");
            assert_eq!(numeric(a), typed_values(code, 24), "{name} {code}_{order}");
        }
    }
    let big = array(&root, "f8_big");
    assert_eq!(
        (big.element(), big.shape()),
        (Element::F64, &[3usize, 2][..])
    );
    assert_eq!(numeric(big), typed_values("f8", 6), "{name} f8_big");
    let big_fortran = array(&root, "u2_big_f");
    assert_eq!(
        numeric(big_fortran),
        typed_values("u2", 6),
        "{name} u2_big_f"
    );
    let empty = array(&root, "f4_empty");
    assert_eq!((empty.shape(), empty.len()), (&[0usize, 3][..], 0));
    let zero_d = array(&root, "f4_0d");
    assert_eq!((zero_d.shape(), numeric(zero_d)), (&[][..], vec![2.5]));
    assert_eq!(
        array(&root, "scalar_f8").data(),
        &ArrayData::F64(vec![1.25])
    );
    assert_eq!(array(&root, "scalar_i4").data(), &ArrayData::I32(vec![-7]));
    assert_eq!(
        array(&root, "scalar_b").data(),
        &ArrayData::Bool(vec![true])
    );
    assert_eq!(
        root.get("py"),
        Some(&Value::List(vec![
            Value::None,
            Value::Bool(true),
            Value::Bool(false),
            Value::Int(3),
            Value::Int(-300),
            Value::Int(70000),
            Value::Int(1 << 40),
            Value::Int(-(1 << 62)),
            Value::Float(1.5),
            Value::Str("héllo".into()),
            Value::Bytes(b"raw".to_vec()),
            Value::Tuple(vec![Value::Int(1), Value::Str("two".into())]),
        ])),
        "{name} py"
    );
    let Some(Value::List(nested)) = root.get("nested").and_then(|n| n.get("list")) else {
        panic!("{name}: nested.list missing");
    };
    assert_eq!(nested.len(), 2);
}

#[test]
fn every_dtype_and_order_reads_under_protocols_2_to_5() {
    for protocol in 2..=5 {
        check_payload(&format!("pickles/arrays_p{protocol}.pkl"));
    }
}

#[test]
fn numpy_1_module_names_read() {
    let bytes = read("pickles/arrays_p2_numpy1.pkl");
    assert!(bytes.windows(10).any(|w| w == b"numpy.core"));
    check_payload("pickles/arrays_p2_numpy1.pkl");
}

#[test]
fn memoised_arrays_are_shared_values() {
    let root = from_slice(&read("pickles/shared_p4.pkl")).expect("valid");
    let Value::List(items) = &root else {
        panic!("expected a list, found {root:?}");
    };
    assert_eq!(items[0], items[1]);
    assert_eq!(items[2].get("again"), Some(&items[0]));
    // Three uses of a 32-byte array do not fit in 64 result bytes.
    let tight = Limits {
        max_result_bytes: 64,
        ..Limits::default()
    };
    let err = from_slice_with_limits(&read("pickles/shared_p4.pkl"), &tight).expect_err("over");
    assert!(err.problem.contains("limit on bytes"), "{err}");
}

fn error_of(bytes: &[u8]) -> String {
    match from_slice(bytes) {
        Ok(v) => panic!("expected an error, got {v:?}"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn hostile_pickles_are_errors() {
    // Empty, truncated, unknown opcode, trailing bytes.
    assert!(error_of(b"").contains("truncated"));
    assert!(error_of(b"\x80\x04\x95").contains("truncated"));
    assert!(error_of(b"\x80\x02\xff.").contains("opcode 0xff"));
    assert!(error_of(b"\x80\x02N.N").contains("after the end"));
    assert!(error_of(b"\x80\x09N.").contains("protocol 9"));
    // A length field far beyond the input must not allocate.
    assert!(error_of(b"\x80\x04\x8e\xff\xff\xff\xff\xff\xff\xff\x7f.").contains("length field"));
    assert!(error_of(b"\x80\x04\x8d\x00\x00\x00\x00\x00\x00\x00\x01.").contains("length field"));
    // Arbitrary globals are refused.
    assert!(error_of(b"\x80\x02cos\nsystem\nq\x00.").contains("os.system is not allowed"));
    // Memo misuse and stack underflow.
    assert!(error_of(b"\x80\x02h\x05.").contains("memo entry 5"));
    assert!(error_of(b"\x80\x02s.").contains("underflow"));
    assert!(error_of(b"\x80\x02N(\x85.").contains("underflow"));
    assert!(error_of(b"\x80\x02e.").contains("MARK"));
    // A dtype nobody supports, and a callable left in the result.
    assert!(error_of(b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00U5\x85R.").contains("'U5'"));
    assert!(error_of(b"\x80\x02cnumpy\ndtype\n.").contains("cannot be part of the result"));
    // An integer beyond 64 bits.
    assert!(error_of(b"\x80\x02\x8a\x09\x00\x00\x00\x00\x00\x00\x00\x00\x01.").contains("64 bits"));
    // LONG1 that does fit.
    assert_eq!(
        from_slice(b"\x80\x02\x8a\x09\xff\xff\xff\xff\xff\xff\xff\xff\xff.").expect("-1"),
        Value::Int(-1)
    );
}

#[test]
fn deep_nesting_and_exponential_sharing_hit_limits_without_overflowing_the_stack() {
    // 100 000 nested lists: EMPTY_LIST, then (EMPTY_LIST APPEND-into-parent) via BINPUT/BINGET chains
    // would be long; instead nest with MARK ... LIST, which pickle also emits.
    let depth = 100_000;
    let mut deep = b"\x80\x02".to_vec();
    deep.extend(std::iter::repeat_n(b'(', depth));
    deep.push(b'N');
    deep.extend(std::iter::repeat_n(b'l', depth));
    deep.push(b'.');
    assert!(error_of(&deep).contains("nesting depth"));

    // L0 = [None]; L(k+1) = [Lk, Lk]: 2^40 values if expanded.
    let mut doubling = b"\x80\x02(Nlq\x00".to_vec();
    for k in 0..40u8 {
        doubling.extend([b'(', b'h', k, b'h', k, b'l', b'q', k + 1]);
    }
    doubling.push(b'.');
    let tight = Limits {
        max_depth: 64,
        max_nodes: 1_000_000,
        ..Limits::default()
    };
    let err = from_slice_with_limits(&doubling, &tight).expect_err("too many values");
    assert!(err.problem.contains("limit on values"), "{err}");

    // A list that contains itself.
    let recursive = b"\x80\x02]q\x00h\x00a.";
    assert!(error_of(recursive).contains("nesting depth"));
}

#[test]
fn array_state_mismatches_are_errors() {
    // _reconstruct then BUILD with a shape needing 8 bytes but 4 given.
    let mut p =
        b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"
            .to_vec();
    p.extend(b"(K\x01K\x02\x86cnumpy\ndtype\nX\x02\x00\x00\x00f4\x85R\x89C\x04\x00\x00\x00\x00tb.");
    assert!(error_of(&p).contains("needs 8 data bytes, found 4"));
    // The same with a negative dimension.
    let mut p =
        b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"
            .to_vec();
    p.extend(b"(J\xff\xff\xff\xff\x85cnumpy\ndtype\nX\x02\x00\x00\x00f4\x85R\x89C\x00tb.");
    assert!(error_of(&p).contains("negative dimension"));
    // An array whose BUILD never came.
    let p = b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R.";
    assert!(error_of(p).contains("BUILD missing"));
}

/// SplitMix64: a tiny deterministic generator, so failures reproduce.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut data = seed.to_vec();
    let edits = 1 + rng.below(4);
    for _ in 0..edits {
        if data.is_empty() {
            data.push(rng.next() as u8);
            continue;
        }
        let at = rng.below(data.len());
        match rng.below(7) {
            0 => data[at] ^= 1 << rng.below(8),
            1 => data[at] = rng.next() as u8,
            2 => data.truncate(at),
            3 => {
                let extra: Vec<u8> = (0..1 + rng.below(8)).map(|_| rng.next() as u8).collect();
                data.splice(at..at, extra);
            }
            4 => {
                // Extreme little-endian values where length and index fields live.
                let width = [1, 2, 4, 8][rng.below(4)];
                let fill = [0x00, 0xff, 0x7f][rng.below(3)];
                let end = (at + width).min(data.len());
                data[at..end].fill(fill);
            }
            5 => {
                let end = (at + 1 + rng.below(16)).min(data.len());
                data.drain(at..end);
            }
            _ => {
                // Duplicate a span (repeats opcodes, shifts lengths).
                let end = (at + 1 + rng.below(32)).min(data.len());
                let span = data[at..end].to_vec();
                let to = rng.below(data.len());
                data.splice(to..to, span);
            }
        }
    }
    data
}

#[test]
fn mutation_fuzzer_never_panics() {
    let mut seeds: Vec<(String, Vec<u8>)> = Vec::new();
    for dir in ["pickles", "phystwin_bad"] {
        let mut names: Vec<PathBuf> = std::fs::read_dir(fixtures().join(dir))
            .expect("fixture dir")
            .map(|e| e.expect("entry").path())
            .collect();
        names.sort();
        for path in names {
            seeds.push((
                path.display().to_string(),
                std::fs::read(&path).expect("read"),
            ));
        }
    }
    for name in ["final_data.pkl", "calibrate.pkl"] {
        seeds.push((name.into(), read(&format!("phystwin_tiny/{name}"))));
    }
    // Small limits so that mutated length fields cannot make a case slow.
    let limits = Limits {
        max_input_bytes: 1 << 20,
        max_depth: 64,
        max_nodes: 100_000,
        max_result_bytes: 1 << 20,
    };
    let cases_per_seed = 1500;
    let mut rng = Rng(0x005e_ed0f_d1ce);
    let (mut ok, mut failed) = (0usize, 0usize);
    for (name, seed) in &seeds {
        for case in 0..cases_per_seed {
            let input = mutate(seed, &mut rng);
            let outcome = std::panic::catch_unwind(|| from_slice_with_limits(&input, &limits));
            match outcome {
                Ok(Ok(_)) => ok += 1,
                Ok(Err(e)) => {
                    assert!(!e.problem.is_empty());
                    failed += 1;
                }
                Err(_) => panic!(
                    "unpickler panicked on mutation {case} of {name}; input (hex): {}",
                    input.iter().map(|b| format!("{b:02x}")).collect::<String>()
                ),
            }
        }
    }
    assert_eq!(ok + failed, seeds.len() * cases_per_seed);
    // The fuzzer must reach past the first opcode: most mutants fail somewhere.
    assert!(failed > ok, "ok {ok}, failed {failed}");
}

#[test]
fn rarer_opcodes_read() {
    // Opcodes numpy pickles of the fixtures do not happen to use, one each.
    let mut p = b"\x80\x04]".to_vec();
    p.extend(b"M\x10\x27a"); // BININT2 10000, APPEND
    p.extend(b"\x8d\x02\x00\x00\x00\x00\x00\x00\x00hia"); // BINUNICODE8
    p.extend(b"\x8e\x03\x00\x00\x00\x00\x00\x00\x00abca"); // BINBYTES8
    p.extend(b"c__builtin__\nbytes\n)\x81a"); // NEWOBJ bytes()
    p.extend(b"(K\x01K\x02la"); // MARK ... LIST
    p.extend(b"(X\x01\x00\x00\x00kK\x05da"); // MARK ... DICT
    p.extend(b"\x8b\x02\x00\x00\x00\xff\x7fa"); // LONG4 32767
    p.extend(b"U\x02xya"); // SHORT_BINSTRING (Python 2 str) as bytes
    p.extend(b"N0"); // NONE, POP
    p.extend(b"2K\x07a0."); // DUP the list, append to the copy (the same object), POP it
    assert_eq!(
        from_slice(&p).expect("valid"),
        Value::List(vec![
            Value::Int(10000),
            Value::Str("hi".into()),
            Value::Bytes(b"abc".to_vec()),
            Value::Bytes(Vec::new()),
            Value::List(vec![Value::Int(1), Value::Int(2)]),
            Value::Dict(vec![(Value::Str("k".into()), Value::Int(5))]),
            Value::Int(32767),
            Value::Bytes(b"xy".to_vec()),
            Value::Int(7),
        ])
    );
}
