//! Throughput of the CPU's dot-product instructions that `--dtype f32|bf16|int8` use, one core:
//! `vfmadd231ps` (f32, 16 multiply-adds), `vdpbf16ps` (bf16 pairs into f32, 32) and `vpdpbusd`
//! (u8·i8 quadruples into i32, 64), each over 12 independent accumulators (more than the
//! latency × throughput product, so that the issue rate is what is measured).
//!
//! ```text
//! cargo run --release -p moma-depth --example dot_throughput
//! ```

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx512f,fma")]
    pub fn fma(n: usize) -> f32 {
        let mut a = [_mm512_setzero_ps(); 12];
        let (x, y) = (_mm512_set1_ps(1.0), _mm512_set1_ps(1e-30));
        for _ in 0..n {
            for a in &mut a {
                *a = _mm512_fmadd_ps(x, y, *a);
            }
        }
        _mm512_reduce_add_ps(
            a.iter()
                .fold(_mm512_setzero_ps(), |s, &a| _mm512_add_ps(s, a)),
        )
    }

    #[target_feature(enable = "avx512f,avx512bf16")]
    pub fn bf16(n: usize) -> f32 {
        let mut a = [_mm512_setzero_ps(); 12];
        // 1.0 and 2⁻⁷ as bf16 pairs (`__m512bh` holds 32 bf16 in 64 bytes, as `__m512i`)
        let (x, y) = (
            _mm512_cvtne2ps_pbh(_mm512_set1_ps(1.0), _mm512_set1_ps(1.0)),
            _mm512_cvtne2ps_pbh(_mm512_set1_ps(0.0078125), _mm512_set1_ps(0.0078125)),
        );
        for _ in 0..n {
            for a in &mut a {
                *a = _mm512_dpbf16_ps(*a, x, y);
            }
        }
        _mm512_reduce_add_ps(
            a.iter()
                .fold(_mm512_setzero_ps(), |s, &a| _mm512_add_ps(s, a)),
        )
    }

    #[target_feature(enable = "avx512f,avx512vnni")]
    pub fn vnni(n: usize) -> i32 {
        let mut a = [_mm512_setzero_si512(); 12];
        let (x, y) = (_mm512_set1_epi32(0x0101_0101), _mm512_set1_epi32(0));
        for _ in 0..n {
            for a in &mut a {
                *a = _mm512_dpbusd_epi32(*a, x, y);
            }
        }
        _mm512_reduce_add_epi32(
            a.iter()
                .fold(_mm512_setzero_si512(), |s, &a| _mm512_add_epi32(s, a)),
        )
    }
}

fn main() {
    #[cfg(target_arch = "x86_64")]
    {
        use std::time::Instant;
        let has = is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx512bf16")
            && is_x86_feature_detected!("avx512vnni")
            && is_x86_feature_detected!("fma");
        if !has {
            println!("this CPU lacks AVX512F, AVX512-BF16, AVX512-VNNI or FMA");
            return;
        }
        let n = 20_000_000;
        let ins = (n * 12) as f64;
        for _ in 0..2 {
            let t = Instant::now();
            // SAFETY: the features were checked above.
            let r1 = unsafe { x86::fma(n) };
            let f = t.elapsed().as_secs_f64();
            let t = Instant::now();
            // SAFETY: as above.
            let r2 = unsafe { x86::bf16(n) };
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            // SAFETY: as above.
            let r3 = unsafe { x86::vnni(n) };
            let v = t.elapsed().as_secs_f64();
            println!(
                "vfmadd231ps zmm {:.3} ns ({:.1} GMAC/s) | vdpbf16ps zmm {:.3} ns ({:.1} GMAC/s) | \
                 vpdpbusd zmm {:.3} ns ({:.1} GMAC/s) per instruction [sums {r1:.1e} {r2:.1e} {r3}]",
                f / ins * 1e9,
                ins * 16.0 / f / 1e9,
                b / ins * 1e9,
                ins * 32.0 / b / 1e9,
                v / ins * 1e9,
                ins * 64.0 / v / 1e9
            );
        }
    }
}
