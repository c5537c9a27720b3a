//! Compares ways to compress an archive's artifacts: each alone, with per-target
//! dictionaries of several sizes and levels, and as compressed groups of similar artifacts
//! (one shader and target, cut at several sizes), printing sizes and the median time to
//! decompress what one lookup needs. The numbers behind the choice documented at the top of
//! `src/archive/format.rs`.
//!
//! `cargo run --release -p kiln --example zstd_probe -- ARCHIVE`

use kiln::archive::{Archive, Target};
use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

fn main() {
    let path = std::env::args().nth(1).unwrap();
    let a = Archive::open(std::path::Path::new(&path)).unwrap();
    // distinct blobs by first use in name-sorted order; group key (shader idx, target)
    let mut perms: Vec<_> = a.permutations().unwrap().collect();
    perms.sort_by(|x, y| x.name().cmp(y.name()));
    let mut seen = HashMap::new();
    let mut blobs: Vec<(Target, u32, Vec<u8>)> = vec![];
    for p in &perms {
        for t in p.targets() {
            let id = p.blob_id(t).unwrap();
            if seen.insert(id, ()).is_none() {
                blobs.push((t, p.record().shader, a.blob(id).unwrap().to_vec()));
            }
        }
    }
    let raw: usize = blobs.iter().map(|b| b.2.len()).sum();
    println!("archive {} bytes, {} distinct blobs, raw {}", a.len(), blobs.len(), raw);
    for level in [3, 9, 19] {
        let t0 = Instant::now();
        let c: usize = blobs.iter().map(|b| zstd::bulk::compress(&b.2, level).unwrap().len()).sum();
        println!("per-blob L{level}: {c} ({:.2}x) {:?}", raw as f64 / c as f64, t0.elapsed());
    }
    let by_target = |t: Target| blobs.iter().filter(move |b| b.0 == t).map(|b| &b.2[..]);
    for dsize in [32 << 10, 64 << 10, 128 << 10, 256 << 10] {
        for level in [3, 19] {
            let mut total = 0;
            let mut dtot = 0;
            let mut times = vec![];
            let t0 = Instant::now();
            for t in Target::ALL {
                let samples: Vec<&[u8]> = by_target(t).collect();
                if samples.is_empty() {
                    continue;
                }
                let dict = zstd::dict::from_samples(&samples, dsize).unwrap();
                dtot += dict.len();
                let mut comp = zstd::bulk::Compressor::with_dictionary(level, &dict).unwrap();
                let mut dec = zstd::bulk::Decompressor::with_dictionary(&dict).unwrap();
                for s in &samples {
                    let c = comp.compress(s).unwrap();
                    total += c.len();
                    let t1 = Instant::now();
                    let d = dec.decompress(&c, s.len()).unwrap();
                    times.push(t1.elapsed().as_secs_f64() * 1e6);
                    assert_eq!(d.len(), s.len());
                }
            }
            println!(
                "per-target dict {}K L{level}: {} + dicts {} = {} ({:.2}x) dec median {:.1}us (reused ctx) time {:?}",
                dsize >> 10,
                total,
                dtot,
                total + dtot,
                raw as f64 / (total + dtot) as f64,
                median(times),
                t0.elapsed()
            );
        }
    }
    // groups
    for cap in [64usize << 10, 256 << 10, 1 << 20, usize::MAX] {
        for level in [3, 19] {
            let mut groups: BTreeMap<(u32, Target), Vec<Vec<&[u8]>>> = BTreeMap::new();
            for b in &blobs {
                let g = groups.entry((b.1, b.0)).or_default();
                let need_new = match g.last() {
                    None => true,
                    Some(last) => last.iter().map(|x| x.len()).sum::<usize>() + b.2.len() > cap && !last.is_empty(),
                };
                if need_new {
                    g.push(vec![]);
                }
                g.last_mut().unwrap().push(&b.2);
            }
            let mut total = 0;
            let mut times = vec![];
            let mut n = 0;
            let t0 = Instant::now();
            for chunks in groups.values() {
                for chunk in chunks {
                    n += 1;
                    let cat: Vec<u8> = chunk.concat();
                    let c = zstd::bulk::compress(&cat, level).unwrap();
                    total += c.len();
                    let t1 = Instant::now();
                    let d = zstd::bulk::decompress(&c, cat.len()).unwrap();
                    let el = t1.elapsed().as_secs_f64() * 1e6;
                    assert_eq!(d.len(), cat.len());
                    for _ in chunk {
                        times.push(el);
                    }
                }
            }
            println!(
                "groups cap {}K L{level}: {n} groups {} ({:.2}x) lookup dec median {:.1}us time {:?}",
                if cap == usize::MAX { 0 } else { cap >> 10 },
                total,
                raw as f64 / total as f64,
                median(times),
                t0.elapsed()
            );
        }
    }
}
