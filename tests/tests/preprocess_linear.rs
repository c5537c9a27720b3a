//! Preprocessing cost grows linearly with the input (issue 16, section 4): the inputs that
//! were quadratic (per-token work that rescanned the line, the argument list or the
//! definition) run at two sizes, four times apart.
//!
//! Memory is measured exactly, by a counting global allocator: the peak of live heap bytes
//! during one run. Time is not asserted; each case runs under a generous cap (a thread and a
//! channel) sized so that the old quadratic behaviour (20 s for 400,000 `__LINE__` in a
//! release build) cannot pass while linear work takes well under a second.
//!
//! Everything runs in one test function: the allocator's counters are global, so no other
//! test may allocate at the same time.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use kiln::preprocess::{self, Options, SourceCache};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call is passed on unchanged to the system allocator; the counters only
// observe sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's guarantees for `layout` are the system allocator's.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator, that is from the system one, with `layout`.
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as for dealloc; `new_size` is the caller's, checked by it.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::Relaxed) + new_size - layout.size();
                PEAK.fetch_max(now, Ordering::Relaxed);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Far above what linear work needs in a debug build on a loaded machine, far below what the
/// quadratic versions took at these sizes.
const CAP: Duration = Duration::from_secs(60);

/// What one run did: whether it succeeded (or the error message), and the peak heap bytes
/// above what was live before it started (the input text included).
struct Run {
    result: Result<usize, String>,
    peak: usize,
}

fn run(what: &str, text: String) -> Run {
    let (tx, rx) = mpsc::channel();
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let worker = std::thread::spawn(move || {
        let cache = SourceCache::new(std::env::temp_dir());
        let id = cache.add_virtual("big.usf", &text);
        drop(text);
        let opts = Options { max_output_bytes: 64 << 20, ..Options::default() };
        let r = preprocess::preprocess_file_id(id, &opts, &cache);
        let _ = tx.send(r.map(|o| o.text.len()).map_err(|e| e.to_string()));
    });
    let result = match rx.recv_timeout(CAP) {
        Ok(r) => r,
        Err(_) => panic!("{what}: no answer within {CAP:?}: preprocessing is not linear in the input"),
    };
    worker.join().expect("the worker ends");
    let peak = PEAK.load(Ordering::Relaxed).saturating_sub(base);
    Run { result, peak }
}

/// Runs `make(n)` and `make(4 * n)`: both must give `expect`'s answer, and the larger may
/// use at most `4 * growth_slack` times the memory of the smaller (quadratic: 16 times).
#[track_caller]
fn two_sizes(what: &str, n: usize, make: impl Fn(usize) -> String, expect: impl Fn(&Result<usize, String>) -> bool) {
    let small = make(n);
    let large = make(4 * n);
    let (small_len, large_len) = (small.len(), large.len());
    let a = run(what, small);
    let b = run(what, large);
    assert!(expect(&a.result), "{what} at {n}: {:?}", a.result);
    assert!(expect(&b.result), "{what} at {}: {:?}", 4 * n, b.result);
    eprintln!(
        "{what}: {small_len} bytes in, peak {} bytes; {large_len} bytes in, peak {} bytes ({:.2}x)",
        a.peak,
        b.peak,
        b.peak as f64 / a.peak.max(1) as f64
    );
    assert!(
        b.peak <= 6 * a.peak.max(1 << 16),
        "{what}: memory grows faster than the input: {} then {}",
        a.peak,
        b.peak
    );
}

#[test]
fn cost_is_linear_in_the_input() {
    // One line of `__LINE__`s (the line's column was counted for each).
    two_sizes("__LINE__ on one line", 200_000, |n| "__LINE__ ".repeat(n) + "\n", |r| r.is_ok());

    // A call with many arguments (the argument list was summed at each token): the error
    // comes at once.
    two_sizes(
        "a call with too many arguments",
        100_000,
        |n| format!("#define F(x) x\nF({})\n", vec!["a"; n].join(",")),
        |r| r.as_ref().is_err_and(|e| e.contains("passed") && e.contains("takes just 1")),
    );
    two_sizes(
        "a variadic call with many arguments",
        100_000,
        |n| format!("#define F(...) f(__VA_ARGS__)\nF({})\n", vec!["a"; n].join(",")),
        |r| r.is_ok(),
    );

    // A definition with many parameters, and a body naming them (a linear search per token).
    two_sizes(
        "many parameters",
        10_000,
        |n| {
            let p: Vec<String> = (0..n).map(|i| format!("p{i}")).collect();
            format!("#define F({}) {}\n", p.join(","), p.join(" + "))
        },
        |r| r.is_ok(),
    );

    // A chain of pastes (the growing token was copied, lexed and interned at each step).
    two_sizes(
        "a chain of ## pastes",
        20_000,
        |n| format!("#define P {}\nP\n", vec!["a"; n].join(" ## ")),
        |r| r.as_ref().is_ok_and(|&len| len > 0),
    );

    // A body naming a long argument many times: the list was built whole before the token
    // budget saw it (2 GB for a 40 kB input), and each `#x` stringified it again.
    for (what, make) in [
        (
            "a parameter named many times",
            (|n: usize| format!("#define S(x) {}\nS({})\n", "x ".repeat(n), "a ".repeat(n))) as fn(usize) -> String,
        ),
        ("a parameter stringified many times", |n| {
            format!("#define S(x) {}\nS({})\n", "#x ".repeat(n), "a ".repeat(n))
        }),
        ("__VA_OPT__ stringified many times", |n| {
            format!("#define S(...) {}\nS({})\n", "#__VA_OPT__(__VA_ARGS__) ".repeat(n), "a ".repeat(n))
        }),
    ] {
        for n in [2_500, 10_000] {
            let r = run(what, make(n));
            eprintln!(
                "{what} ({n}): peak {} bytes, {:?}",
                r.peak,
                r.result.as_ref().map_err(|e| &e[..e.len().min(60)])
            );
            // n² is near or over the output budget: a clean error or the output, in bounded memory.
            if let Err(e) = &r.result {
                assert!(e.starts_with("macro expansion makes more than") || e.starts_with("output exceeds"), "{e}");
            }
            assert!(r.peak < 256 << 20, "{what} ({n}): {} bytes", r.peak);
        }
    }

    // A long definition never used costs about its text (it took 36 times its size).
    for n in [1_000_000usize, 4_000_000] {
        let text = format!("#define BIG {}\nx\n", "a ".repeat(n));
        let len = text.len();
        let r = run("a long unused definition", text);
        assert!(r.result.is_ok(), "{:?}", r.result);
        eprintln!("unused definition: {len} bytes in, peak {} bytes ({:.2}x)", r.peak, r.peak as f64 / len as f64);
        // The text (twice: the caller's copy and the cache's) and its token table (4 bytes
        // per byte); no per-token storage.
        assert!(r.peak <= 7 * len, "a {len}-byte unused definition took {} bytes", r.peak);
    }

    // The same definition used: its tokens are made then (and bounded by the budget).
    let text = format!("#define BIG {}\nBIG\n", "a ".repeat(100_000));
    let r = run("a long used definition", text);
    assert_eq!(r.result, Ok(200_000), "the expansion prints every token");
}
