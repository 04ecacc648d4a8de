//! A linear layer y = x·W + b as one Burn backend extension, forward and backward.
//!
//! Every decoder and entropy model of a training step is a small MLP (widths 5-72) over all
//! anchors (10⁴-10⁵ rows). Through Burn's `matmul` and broadcast `add`, ndarray spends most of that
//! in overhead rather than arithmetic: matrixmultiply packs both operands and hands each product
//! to its own thread tree, the backward's `xᵀ·dy` walks a transposed view, and the bias gradient is
//! a `sum_dim` over a dynamic-rank array — 10-15 % of a CPU training step's samples (`perf`,
//! issue 21). Here the CPU twin walks chunks of rows on rayon's pool: each row's output (or input
//! gradient) is a few vector multiply-adds over a weight matrix that stays in the L1 cache, and
//! the weight and bias gradients are summed per chunk of [`ROWS`] rows, then over the chunks in
//! chunk order, so the result does not depend on the number of threads. The Cube (wgpu) version is
//! Burn's own `matmul`, `add` and `sum_dim` on the device's inner tensors.
//!
//! Sums run in another order than matrixmultiply's blocked products, so values differ from
//! `x.matmul(w) + b` in the last bits (the tests bound it). The forward sums b + x₀w₀ + x₁w₁ + …
//! in input order, as the coder's host MLP does (`codec::entropy_models::HostMlp`).

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Tensor, TensorData};
use burn_cubecl::CubeBackend;
use rayon::prelude::*;

use crate::backend::{HostIo, with_floats};
use crate::host_simd::{Lanes, avx2_twin};

/// Rows per parallel chunk of the CPU twin. Fixed (not derived from the thread count), so the
/// chunk partial sums of the weight gradient, and their order, are the same on every machine.
pub const ROWS: usize = 256;

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait LinearBackend: Backend {
    /// `x` [M, I] · `weight` [I, O] + `bias` [O] → [M, O].
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// ∂/∂x of Σ grad ⊙ linear: `grad` [M, O] · weightᵀ → [M, I].
    fn linear_input_grad(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self>;

    /// (∂/∂weight, ∂/∂bias) of Σ grad ⊙ linear: (xᵀ · grad [I, O], Σ_rows grad [O]).
    fn linear_parameter_grads(
        x: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

fn dims2<T: TensorMetadata>(t: &T, what: &str) -> (usize, usize) {
    let shape = t.shape();
    assert_eq!(
        shape.num_dims(),
        2,
        "linear: `{what}` must be [rows, columns], got {} dimensions",
        shape.num_dims()
    );
    (shape[0], shape[1])
}

/// Outputs per block: one AVX2 register of f32.
const LANES: usize = 8;
/// Rows per block of the products: 4 rows × 8 outputs of sums stay in registers.
const ROW_BLOCK: usize = 4;

fn round_up(n: usize, to: usize) -> usize {
    n.div_ceil(to) * to
}

/// `rows` rows of `width` values from `src` into a zeroed [rows_padded, padded] buffer.
fn padded(src: &[f32], width: usize, rows_padded: usize, padded: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; rows_padded * padded];
    if width > 0 {
        for (d, s) in out.chunks_exact_mut(padded).zip(src.chunks_exact(width)) {
            d[..width].copy_from_slice(s);
        }
    }
    out
}

avx2_twin! {
    /// `out` [R, P] = `bias` [P] + `x` [R, I] · `weight` [I, P], R a multiple of [`ROW_BLOCK`] and
    /// P of [`LANES`]; every output summed as bias + x₀w₀ + x₁w₁ + … in input order.
    fn product_blocks(x: &[f32], weight: &[f32], bias: &[f32], out: &mut [f32], input: usize, padded_out: usize) {
        let blocks = padded_out / LANES;
        for (xs, ys) in x
            .chunks_exact(ROW_BLOCK * input)
            .zip(out.chunks_exact_mut(ROW_BLOCK * padded_out))
        {
            for b in 0..blocks {
                let start: [f32; LANES] = bias[b * LANES..][..LANES].try_into().unwrap();
                let mut acc = [start; ROW_BLOCK];
                for i in 0..input {
                    let w: [f32; LANES] = weight[i * padded_out + b * LANES..][..LANES]
                        .try_into()
                        .unwrap();
                    for (r, sums) in acc.iter_mut().enumerate() {
                        let xr = xs[r * input + i];
                        for l in 0..LANES {
                            sums[l] += xr * w[l];
                        }
                    }
                }
                for (r, sums) in acc.iter().enumerate() {
                    ys[r * padded_out + b * LANES..][..LANES].copy_from_slice(sums);
                }
            }
        }
    }
}

avx2_twin! {
    /// `dw` [I, P] = xᵀ · `g` and `db` [P] = Σ_rows g over `rows` rows, each sum from 0 in row
    /// order (`x` [rows, I], I a multiple of [`ROW_BLOCK`]; `g` [rows, P], P of [`LANES`]).
    fn transposed_product_blocks(x: &[f32], g: &[f32], dw: &mut [f32], db: &mut [f32], rows: usize, padded_in: usize, padded_out: usize) {
        for b in 0..padded_out / LANES {
            let lanes_of = |r: usize| -> [f32; LANES] {
                g[r * padded_out + b * LANES..][..LANES].try_into().unwrap()
            };
            let mut sum = [0.0f32; LANES];
            for r in 0..rows {
                let gv = lanes_of(r);
                for l in 0..LANES {
                    sum[l] += gv[l];
                }
            }
            db[b * LANES..][..LANES].copy_from_slice(&sum);
            for i0 in (0..padded_in).step_by(ROW_BLOCK) {
                let mut acc = [[0.0f32; LANES]; ROW_BLOCK];
                for r in 0..rows {
                    let gv = lanes_of(r);
                    for (q, sums) in acc.iter_mut().enumerate() {
                        let xq = x[r * padded_in + i0 + q];
                        for l in 0..LANES {
                            sums[l] += xq * gv[l];
                        }
                    }
                }
                for (q, sums) in acc.iter().enumerate() {
                    dw[(i0 + q) * padded_out + b * LANES..][..LANES].copy_from_slice(sums);
                }
            }
        }
    }
}

/// `out` [rows, O] = bias + `x` [rows, I] · `weight` [I, O] for one chunk of rows, through
/// zero-padded copies (rows to [`ROW_BLOCK`], outputs to [`LANES`]).
fn product_chunk(
    lanes: Lanes,
    x: &[f32],
    weight_padded: &[f32],
    bias_padded: &[f32],
    out: &mut [f32],
    input: usize,
    output: usize,
) {
    let padded_out = bias_padded.len();
    let rows = out.len() / output;
    let rows_padded = round_up(rows, ROW_BLOCK);
    let xs = padded(x, input, rows_padded, input);
    let mut ys = vec![0.0f32; rows_padded * padded_out];
    product_blocks(lanes, &xs, weight_padded, bias_padded, &mut ys, input, padded_out);
    for (y, s) in out.chunks_exact_mut(output).zip(ys.chunks_exact(padded_out)) {
        y.copy_from_slice(&s[..output]);
    }
}

/// The CPU twin's forward on host slices (`x` [M, I], `weight` [I, O], `bias` [O]) → [M, O].
pub fn forward_host(
    lanes: Lanes,
    x: &[f32],
    weight: &[f32],
    bias: &[f32],
    [rows, input, output]: [usize; 3],
) -> Vec<f32> {
    let mut out = vec![0.0f32; rows * output];
    if output == 0 {
        return out;
    }
    if input == 0 {
        out.chunks_exact_mut(output)
            .for_each(|y| y.copy_from_slice(bias));
        return out;
    }
    let padded_out = round_up(output, LANES);
    let weight_padded = padded(weight, output, input, padded_out);
    let bias_padded = padded(bias, output, 1, padded_out);
    out.par_chunks_mut(ROWS * output)
        .zip(x.par_chunks(ROWS * input))
        .for_each(|(y, x)| {
            product_chunk(lanes, x, &weight_padded, &bias_padded, y, input, output)
        });
    out
}

/// The CPU twin's input gradient on host slices (`grad` [M, O], `weight` [I, O]) → [M, I]:
/// each element summed from 0 over the outputs in order.
pub fn input_grad_host(
    lanes: Lanes,
    grad: &[f32],
    weight: &[f32],
    input: usize,
    output: usize,
) -> Vec<f32> {
    let rows = grad.len() / output.max(1);
    let mut dx = vec![0.0f32; rows * input];
    if input == 0 || output == 0 {
        return dx;
    }
    // weightᵀ [O, I], its rows padded to whole blocks of lanes.
    let padded_in = round_up(input, LANES);
    let mut transposed = vec![0.0f32; output * padded_in];
    for (i, w) in weight.chunks_exact(output).enumerate() {
        for (o, &v) in w.iter().enumerate() {
            transposed[o * padded_in + i] = v;
        }
    }
    let zeros = vec![0.0f32; padded_in];
    dx.par_chunks_mut(ROWS * input)
        .zip(grad.par_chunks(ROWS * output))
        .for_each(|(d, g)| product_chunk(lanes, g, &transposed, &zeros, d, output, input));
    dx
}

/// The CPU twin's parameter gradients on host slices (`x` [M, I], `grad` [M, O]) →
/// ([I, O], [O]): per chunk of [`ROWS`] rows (each sum from 0 in row order), then over the
/// chunks in order.
pub fn parameter_grads_host(
    lanes: Lanes,
    x: &[f32],
    grad: &[f32],
    input: usize,
    output: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (mut dw, mut db) = (vec![0.0f32; input * output], vec![0.0f32; output]);
    if output == 0 {
        return (dw, db);
    }
    let rows = grad.len() / output;
    let (padded_in, padded_out) = (round_up(input, ROW_BLOCK), round_up(output, LANES));
    let partials: Vec<(Vec<f32>, Vec<f32>)> = grad
        .par_chunks(ROWS * output)
        .enumerate()
        .map(|(c, g)| {
            let chunk_rows = g.len() / output;
            let r0 = c * ROWS;
            let xs = padded(
                &x[(r0 * input).min(x.len())..((r0 + chunk_rows) * input).min(x.len())],
                input,
                chunk_rows,
                padded_in,
            );
            let gs = padded(g, output, chunk_rows, padded_out);
            let (mut pw, mut pb) = (vec![0.0f32; padded_in * padded_out], vec![0.0f32; padded_out]);
            transposed_product_blocks(
                lanes, &xs, &gs, &mut pw, &mut pb, chunk_rows, padded_in, padded_out,
            );
            (pw, pb)
        })
        .collect();
    debug_assert_eq!(partials.len(), rows.div_ceil(ROWS));
    for (pw, pb) in &partials {
        for (d, p) in dw.chunks_exact_mut(output.max(1)).zip(pw.chunks_exact(padded_out)) {
            d.iter_mut().zip(p).for_each(|(d, &v)| *d += v);
        }
        db.iter_mut().zip(pb).for_each(|(d, &v)| *d += v);
    }
    (dw, db)
}

impl LinearBackend for NdArray {
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let [rows, input, output] = layer_dims(&x, &weight, &bias);
        let device = x.device();
        let (weight, bias) = (NdArray::read_floats(weight), NdArray::read_floats(bias));
        let out = with_floats(x, |x| {
            forward_host(Lanes::Widest, x, &weight, &bias, [rows, input, output])
        });
        NdArray::float_from_data(TensorData::new(out, [rows, output]), &device)
    }

    fn linear_input_grad(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let (rows, output) = dims2(&grad, "grad");
        let (input, w_out) = dims2(&weight, "weight");
        assert_eq!(w_out, output, "linear: the gradient has {output} columns, the weight {w_out}");
        let device = grad.device();
        let weight = NdArray::read_floats(weight);
        let dx = with_floats(grad, |g| {
            input_grad_host(Lanes::Widest, g, &weight, input, output)
        });
        NdArray::float_from_data(TensorData::new(dx, [rows, input]), &device)
    }

    fn linear_parameter_grads(
        x: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (rows, input) = dims2(&x, "x");
        let (g_rows, output) = dims2(&grad, "grad");
        assert_eq!(g_rows, rows, "linear: {rows} input rows, {g_rows} gradient rows");
        let device = x.device();
        // Both straight out of their storage: the gradient is shared with the input gradient's
        // product, so reading it as an owned vector would copy it.
        let (dw, db) = with_floats(grad, |grad| {
            with_floats(x, |x| parameter_grads_host(Lanes::Widest, x, grad, input, output))
        });
        (
            NdArray::float_from_data(TensorData::new(dw, [input, output]), &device),
            NdArray::float_from_data(TensorData::new(db, [output]), &device),
        )
    }
}

/// [rows, input, output] of a layer's operands, checked: `x` [rows, input], `weight`
/// [input, output], `bias` [output]; panics naming the shapes that do not fit.
fn layer_dims<T: TensorMetadata>(x: &T, weight: &T, bias: &T) -> [usize; 3] {
    let (rows, input) = dims2(x, "x");
    let (w_in, output) = dims2(weight, "weight");
    assert_eq!(
        w_in, input,
        "linear: the input has {input} columns, the weight {w_in} rows"
    );
    let shape = bias.shape();
    assert!(
        shape.num_dims() == 1 && shape[0] == output,
        "linear: the bias must be [{output}], got {shape:?}"
    );
    [rows, input, output]
}

/// The wgpu (and CUDA) device: Burn's own matmul, add and sum on the device's inner (unfused)
/// tensors, registered back into the fusion stream as one opaque step, as the rasterizer does.
/// (The decoders do not take this path on a device: see `model::decoders::layer` in acags.)
impl LinearBackend for burn::backend::Cube {
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, register};
        let [rows, _, output] = layer_dims(&x, &weight, &bias);
        let client = x.client.clone();
        let [x, weight, bias] = [x, weight, bias].map(inner_float);
        let product = CubeBackend::float_matmul(x, weight);
        let bias = CubeBackend::float_expand(
            CubeBackend::float_reshape(bias, [1, output].into()),
            [rows, output].into(),
        );
        register(&client, CubeBackend::float_add(product, bias))
    }

    fn linear_input_grad(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, register};
        let client = grad.client.clone();
        let [grad, weight] = [grad, weight].map(inner_float);
        register(
            &client,
            CubeBackend::float_matmul(grad, CubeBackend::float_transpose(weight)),
        )
    }

    fn linear_parameter_grads(
        x: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        use crate::backend::fused::{inner_float, register};
        let (_, output) = dims2(&grad, "grad");
        let client = x.client.clone();
        let [x, grad] = [x, grad].map(inner_float);
        let dw = CubeBackend::float_matmul(CubeBackend::float_transpose(x), grad.clone());
        let db = CubeBackend::float_reshape(CubeBackend::float_sum_dim(grad, 0), [output].into());
        (register(&client, dw), register(&client, db))
    }
}

#[derive(Debug)]
struct LinearBackward;

impl<B: LinearBackend> Backward<B, 3> for LinearBackward {
    /// (x, weight)
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight) = ops.state;
        let [px, pweight, pbias] = ops.parents;
        if pweight.is_some() || pbias.is_some() {
            let (dw, db) = B::linear_parameter_grads(x, grad.clone());
            if let Some(node) = pweight {
                grads.register::<B>(node.id, dw);
            }
            if let Some(node) = pbias {
                grads.register::<B>(node.id, db);
            }
        }
        if let Some(node) = px {
            grads.register::<B>(node.id, B::linear_input_grad(grad, weight));
        }
    }
}

impl<B: LinearBackend, C: CheckpointStrategy> LinearBackend for Autodiff<B, C> {
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (weight, weight_node) = weight.into_parts();
        let (bias, bias_node) = bias.into_parts();
        match LinearBackward
            .prepare::<C>([x_node, weight_node, bias_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::linear_forward(x.clone(), weight.clone(), bias);
                prep.finish((x, weight), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::linear_forward(x, weight, bias)),
        }
    }

    fn linear_input_grad(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        // Only used as a backward: not differentiable itself.
        Self::from_inner(B::linear_input_grad(Self::inner(grad), Self::inner(weight)))
    }

    fn linear_parameter_grads(
        x: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (dw, db) = B::linear_parameter_grads(Self::inner(x), Self::inner(grad));
        (Self::from_inner(dw), Self::from_inner(db))
    }
}

/// `x` [M, I] · `weight` [I, O] + `bias` [O] → [M, O], differentiable in all three, on any
/// backend (with or without autodiff); equal to `x.matmul(weight) + bias` up to the order of the
/// sums. Panics when the shapes do not fit, naming them.
pub fn linear(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as LinearBackend>::linear_forward(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
    ))
}

#[cfg(test)]
mod twin_tests {
    use super::*;

    fn wave(n: usize, f: f32, a: f32) -> Vec<f32> {
        (0..n).map(|k| (k as f32 * f).sin() * a).collect()
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|f| f.to_bits()).collect()
    }

    /// The plain row loops the blocked ones must equal bit for bit: each sum in the same order.
    fn reference(
        x: &[f32],
        w: &[f32],
        b: &[f32],
        g: &[f32],
        [rows, input, output]: [usize; 3],
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut y = vec![0.0f32; rows * output];
        for (row, yr) in x.chunks_exact(input).zip(y.chunks_exact_mut(output)) {
            yr.copy_from_slice(b);
            for (i, &xi) in row.iter().enumerate() {
                for o in 0..output {
                    yr[o] += xi * w[i * output + o];
                }
            }
        }
        let mut dx = vec![0.0f32; rows * input];
        for (gr, dr) in g.chunks_exact(output).zip(dx.chunks_exact_mut(input)) {
            for (o, &go) in gr.iter().enumerate() {
                for i in 0..input {
                    dr[i] += go * w[i * output + o];
                }
            }
        }
        let (mut dw, mut db) = (vec![0.0f32; input * output], vec![0.0f32; output]);
        for c in 0..rows.div_ceil(ROWS) {
            let (mut pw, mut pb) = (vec![0.0f32; input * output], vec![0.0f32; output]);
            for r in c * ROWS..((c + 1) * ROWS).min(rows) {
                for o in 0..output {
                    pb[o] += g[r * output + o];
                    for i in 0..input {
                        pw[i * output + o] += x[r * input + i] * g[r * output + o];
                    }
                }
            }
            dw.iter_mut().zip(&pw).for_each(|(d, &v)| *d += v);
            db.iter_mut().zip(&pb).for_each(|(d, &v)| *d += v);
        }
        (y, dx, dw, db)
    }

    /// Both copies (AVX2, portable) of the blocked loops equal the plain row loops bit for bit,
    /// over row counts that are not multiples of a chunk or a block, and widths that are and
    /// are not multiples of the lanes and of the row block.
    #[test]
    fn the_blocked_loops_equal_the_row_loops_bit_for_bit() {
        for (rows, input, output) in [
            (1000usize, 24usize, 35usize),
            (517, 40, 24),
            (300, 3, 5),
            (7, 48, 1),
            (1, 1, 8),
        ] {
            let x = wave(rows * input, 0.37, 2.0);
            let w = wave(input * output, 0.11, 0.5);
            let b = wave(output, 0.53, 0.3);
            let g = wave(rows * output, 0.29, 1.5);
            let (ry, rdx, rdw, rdb) = reference(&x, &w, &b, &g, [rows, input, output]);
            for lanes in [Lanes::Widest, Lanes::Portable] {
                let y = forward_host(lanes, &x, &w, &b, [rows, input, output]);
                let dx = input_grad_host(lanes, &g, &w, input, output);
                let (dw, db) = parameter_grads_host(lanes, &x, &g, input, output);
                let what = format!("{lanes:?} {rows}x{input}->{output}");
                assert_eq!(bits(&y), bits(&ry), "{what}: forward");
                assert_eq!(bits(&dx), bits(&rdx), "{what}: input gradient");
                assert_eq!(bits(&dw), bits(&rdw), "{what}: weight gradient");
                assert_eq!(bits(&db), bits(&rdb), "{what}: bias gradient");
            }
        }
    }

    /// The row loops against the definitions, summed in f64.
    #[test]
    fn the_row_loops_compute_the_products() {
        let (rows, input, output) = (600usize, 7usize, 9usize);
        let x = wave(rows * input, 0.37, 2.0);
        let w = wave(input * output, 0.11, 0.5);
        let b = wave(output, 0.53, 0.3);
        let g = wave(rows * output, 0.29, 1.5);
        let (y, dx, dw, db) = reference(&x, &w, &b, &g, [rows, input, output]);
        // Within f32 rounding of a sum of n terms: n · 2⁻²⁴ of the terms' absolute sum.
        let close = |a: f32, terms: &[f64], what: &str| {
            let (e, size) = terms
                .iter()
                .fold((0.0f64, 0.0f64), |(s, m), t| (s + t, m + t.abs()));
            let bound = terms.len() as f64 * 6e-8 * size + 1e-12;
            assert!((a as f64 - e).abs() <= bound, "{what}: {a} vs {e} (bound {bound})")
        };
        for r in 0..rows {
            for o in 0..output {
                let mut terms = vec![b[o] as f64];
                terms.extend((0..input).map(|i| x[r * input + i] as f64 * w[i * output + o] as f64));
                close(y[r * output + o], &terms, "y");
            }
            for i in 0..input {
                let terms: Vec<f64> = (0..output)
                    .map(|o| g[r * output + o] as f64 * w[i * output + o] as f64)
                    .collect();
                close(dx[r * input + i], &terms, "dx");
            }
        }
        for i in 0..input {
            for o in 0..output {
                let terms: Vec<f64> = (0..rows)
                    .map(|r| x[r * input + i] as f64 * g[r * output + o] as f64)
                    .collect();
                close(dw[i * output + o], &terms, "dw");
            }
        }
        for o in 0..output {
            let terms: Vec<f64> = (0..rows).map(|r| g[r * output + o] as f64).collect();
            close(db[o], &terms, "db");
        }
    }
}
