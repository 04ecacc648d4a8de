//! ReLU, sigmoid and tanh as one Burn backend extension, forward and backward.
//!
//! Every decoder and entropy model ends its hidden layer in a ReLU, the colour head in a sigmoid,
//! the opacity head in a tanh, and the gates, feature masks and spawned scales are sigmoids.
//! On ndarray Burn computes each as a chain of whole-tensor passes on the step's thread (a
//! sigmoid is exp, add, log, neg, exp; its backward recomputes the sigmoid from the input, then
//! three more passes; a ReLU's backward builds a mask, then fills): ~5 % of an ACA-GS CPU step's
//! samples, all serial (`perf`, issue 21). Here the ndarray twin is one parallel pass each way, on
//! rayon's pool, with the backward taken from the saved output. Each element is computed with
//! Burn's own formulas and f32 operations in Burn's order, so values and gradients are the same to
//! the bit (the tests compare bits; the golden traces did not move), a NaN's sign bit aside (Burn
//! negates by multiplying with −1). The Cube (wgpu) version is
//! Burn's own activation ops, which the fusion backend keeps fusing.

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::{ActivationOps, FloatTensorOps};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::backend::{HostIo, assert_f32, with_floats};

/// An element-wise activation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// max(x, 0).
    Relu,
    /// 1 / (1 + e^−x), computed as Burn does: exp(−ln(e^−x + 1)).
    Sigmoid,
    /// tanh, in f64 as Burn's ndarray backend does.
    Tanh,
}

impl Activation {
    /// y of one element, Burn's ndarray formula and operation order.
    #[inline]
    pub fn value(self, x: f32) -> f32 {
        match self {
            Activation::Relu => {
                if x < 0.0 {
                    0.0
                } else {
                    x
                }
            }
            Activation::Sigmoid => (-((-x).exp() + 1.0).ln()).exp(),
            Activation::Tanh => (x as f64).tanh() as f32,
        }
    }

    /// ∂/∂x of one element times `grad`, from the output `y`, in Burn's order: ReLU
    /// `mask_fill(grad, y ≤ 0, 0)`, sigmoid `(y·(−y + 1))·grad`, tanh `grad·(−y² + 1)`.
    #[inline]
    pub fn gradient(self, y: f32, grad: f32) -> f32 {
        match self {
            Activation::Relu => {
                if y <= 0.0 {
                    0.0
                } else {
                    grad
                }
            }
            Activation::Sigmoid => (y * (-y + 1.0)) * grad,
            Activation::Tanh => grad * (-(y * y) + 1.0),
        }
    }
}

/// Elements per parallel task: a task is a few microseconds of work.
const CHUNK: usize = 4096;

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait ActivationBackend: Backend {
    /// `activation` of every element of `x` (any shape).
    fn activation_forward(x: FloatTensor<Self>, activation: Activation) -> FloatTensor<Self>;

    /// The VJP of [`Self::activation_forward`] from its output `y`: `grad` ⊙ activation′, same
    /// shape.
    fn activation_backward(
        y: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        activation: Activation,
    ) -> FloatTensor<Self>;
}

impl ActivationBackend for NdArray {
    fn activation_forward(x: FloatTensor<Self>, activation: Activation) -> FloatTensor<Self> {
        assert_f32(&x, "activation");
        let shape = x.shape();
        let device = x.device();
        // In place when nothing else holds `x` (usually: a layer's fresh output).
        let mut values = NdArray::read_floats(x);
        values
            .par_chunks_mut(CHUNK)
            .for_each(|c| c.iter_mut().for_each(|v| *v = activation.value(*v)));
        NdArray::float_from_data(TensorData::new(values, shape), &device)
    }

    fn activation_backward(
        y: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        activation: Activation,
    ) -> FloatTensor<Self> {
        assert_f32(&grad, "activation_backward");
        let shape = grad.shape();
        assert_eq!(
            y.shape(),
            shape,
            "activation_backward: the output and its gradient differ in shape"
        );
        let device = grad.device();
        let mut grad = NdArray::read_floats(grad);
        with_floats(y, |y| {
            grad.par_chunks_mut(CHUNK)
                .zip(y.par_chunks(CHUNK))
                .for_each(|(g, y)| {
                    g.iter_mut()
                        .zip(y)
                        .for_each(|(g, &y)| *g = activation.gradient(y, *g))
                })
        });
        NdArray::float_from_data(TensorData::new(grad, shape), &device)
    }
}

/// The wgpu (and CUDA) device: Burn's own ops, recorded into the fusion stream like any other.
impl ActivationBackend for burn::backend::Cube {
    fn activation_forward(x: FloatTensor<Self>, activation: Activation) -> FloatTensor<Self> {
        match activation {
            Activation::Relu => Self::relu(x),
            Activation::Sigmoid => Self::sigmoid(x),
            Activation::Tanh => Self::float_tanh(x),
        }
    }

    fn activation_backward(
        y: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        activation: Activation,
    ) -> FloatTensor<Self> {
        match activation {
            Activation::Relu => Self::relu_backward(y, grad),
            Activation::Sigmoid => Self::sigmoid_backward(y, grad),
            Activation::Tanh => {
                let squared = Self::float_mul(y.clone(), y);
                let derivative = Self::float_add_scalar(Self::float_neg(squared), 1.0.into());
                Self::float_mul(grad, derivative)
            }
        }
    }
}

#[derive(Debug)]
struct ActivationBackward;

impl<B: ActivationBackend> Backward<B, 1> for ActivationBackward {
    /// (the output, which activation).
    type State = (FloatTensor<B>, Activation);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (y, activation) = ops.state;
        let [parent] = ops.parents;
        if let Some(node) = parent {
            grads.register::<B>(node.id, B::activation_backward(y, grad, activation));
        }
    }
}

impl<B: ActivationBackend, C: CheckpointStrategy> ActivationBackend for Autodiff<B, C> {
    fn activation_forward(x: FloatTensor<Self>, activation: Activation) -> FloatTensor<Self> {
        let (x, node) = x.into_parts();
        let y = B::activation_forward(x, activation);
        match ActivationBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((y.clone(), activation), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }

    fn activation_backward(
        y: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        activation: Activation,
    ) -> FloatTensor<Self> {
        // Only used as a backward: not differentiable itself.
        Self::from_inner(B::activation_backward(
            Self::inner(y),
            Self::inner(grad),
            activation,
        ))
    }
}

/// `activation` of every element of `x`, differentiable (any backend, with or without autodiff);
/// equal to Burn's `relu` / `sigmoid` / `tanh`, values and gradients to the bit on ndarray.
pub fn activate<const D: usize>(x: Tensor<D>, activation: Activation) -> Tensor<D> {
    Tensor::<D>::from_dispatch(<Dispatch as ActivationBackend>::activation_forward(
        x.into_dispatch(),
        activation,
    ))
}

/// max(x, 0), as [`activate`].
pub fn relu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    activate(x, Activation::Relu)
}

/// The logistic sigmoid, as [`activate`].
pub fn sigmoid<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    activate(x, Activation::Sigmoid)
}

/// tanh, as [`activate`].
pub fn tanh<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    activate(x, Activation::Tanh)
}
