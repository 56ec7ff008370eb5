// Adam's update of the rows a sparse gradient holds (nerfexp.training.optimizers.lazy_adam_update), in one pass
// over those rows, parallel over them: each touched row's moments and values read once and written once, every
// other row of the parameter left as it is. The arithmetic is torch.optim.Adam's, operation for operation (as
// lazy_adam_update writes it with lerp_, mul_, addcmul_, sqrt, div, add_ and addcdiv_), in float32, equal to it
// within float32 rounding (ATen's vectorized loops may fuse a multiply and an add where this one rounds twice).
//
// Inputs: the parameter, its first and second moments, each [R, D] (contiguous float32, R rows of D values);
// rows [U] (int64, ascending, each in [0, R): distinct, so that no two threads write one row) and their summed
// gradients values [U, D] (float32); the step's scalars (step >= 1, lr >= 0, betas in [0, 1), eps >= 0). A tensor
// on another device (a GPU's: the torch path runs there), not contiguous, of another dtype or shape, a row outside
// the parameter or out of order, and a scalar outside its range are one-line errors, checked before anything is
// written, never a write through a pointer this loop cannot follow.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>

namespace {

// A tensor on the CPU, contiguous, of ``dtype``: what data_ptr and the loop's flat indices read.
void check_cpu_contiguous(const torch::Tensor& t, const char* name, torch::ScalarType dtype = torch::kFloat) {
  TORCH_CHECK(t.device().is_cpu(), "lazy_adam: ", name, " is on ", t.device(), ", not the CPU");
  TORCH_CHECK(t.is_contiguous(), "lazy_adam: ", name, " is not contiguous");
  TORCH_CHECK(t.scalar_type() == dtype, "lazy_adam: ", name, " is ", t.scalar_type(), ", not ",
              dtype == torch::kLong ? "int64" : "float32");
}

// Rows [U] ascending, each in [0, R): one pass over them.
void check_rows(const int64_t* r, int64_t U, int64_t R) {
  for (int64_t i = 0; i < U; ++i) {
    TORCH_CHECK(r[i] >= 0 && r[i] < R, "lazy_adam: row ", r[i], " (rows[", i, "]) is outside the parameter's ", R,
                " rows");
    TORCH_CHECK(i == 0 || r[i] > r[i - 1], "lazy_adam: rows must be ascending, each once: rows[", i, "] = ", r[i],
                " follows ", r[i - 1]);
  }
}

}  // namespace

void lazy_adam_rows(torch::Tensor param, torch::Tensor exp_avg, torch::Tensor exp_avg_sq, torch::Tensor rows,
                    torch::Tensor values, double step, double lr, double beta1, double beta2, double eps) {
  check_cpu_contiguous(param, "param");
  check_cpu_contiguous(exp_avg, "exp_avg");
  check_cpu_contiguous(exp_avg_sq, "exp_avg_sq");
  check_cpu_contiguous(rows, "rows", torch::kLong);
  check_cpu_contiguous(values, "values");
  TORCH_CHECK(step >= 1 && lr >= 0 && beta1 >= 0 && beta1 < 1 && beta2 >= 0 && beta2 < 1 && eps >= 0,
              "lazy_adam: expected step >= 1, lr >= 0, beta1 and beta2 in [0, 1) and eps >= 0, got step ", step,
              ", lr ", lr, ", betas ", beta1, ", ", beta2, ", eps ", eps);
  TORCH_CHECK(param.dim() == 2 && exp_avg.sizes() == param.sizes() && exp_avg_sq.sizes() == param.sizes(),
              "lazy_adam: param, exp_avg and exp_avg_sq must be [R, D] alike, got ", param.sizes(), ", ",
              exp_avg.sizes(), ", ", exp_avg_sq.sizes());
  TORCH_CHECK(rows.dim() == 1 && values.dim() == 2 && values.size(0) == rows.size(0) &&
                  values.size(1) == param.size(1),
              "lazy_adam: rows [U] and values [U, D] of the parameter's D = ", param.size(1), " expected, got ",
              rows.sizes(), " and ", values.sizes());
  const int64_t U = rows.size(0), D = values.size(1);
  float* p = param.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  const int64_t* r = rows.data_ptr<int64_t>();
  const float* g = values.data_ptr<float>();
  check_rows(r, U, param.size(0));
  // the scalars as torch's float32 kernels take them: Python floats converted to the tensors' type
  const float w1 = static_cast<float>(1 - beta1), b2 = static_cast<float>(beta2), w2 = static_cast<float>(1 - beta2);
  const float root_correction2 = static_cast<float>(std::sqrt(1 - std::pow(beta2, step)));
  const float step_size = static_cast<float>(-lr / (1 - std::pow(beta1, step))), epsilon = static_cast<float>(eps);
  at::parallel_for(0, U, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      for (int64_t d = 0; d < D; ++d) {
        const int64_t at = r[i] * D + d;
        const float gradient = g[i * D + d];
        const float first = m[at] + w1 * (gradient - m[at]);  // lerp_(gradient, 1 - beta1), one of its two forms
        const float second = v[at] * b2 + w2 * gradient * gradient;  // mul_(beta2).addcmul_(g, g, 1 - beta2)
        const float denom = std::sqrt(second) / root_correction2 + epsilon;
        m[at] = first;
        v[at] = second;
        p[at] = p[at] + step_size * first / denom;  // addcdiv_(first, denom, value=-lr / bias_correction1)
      }
  });
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rows", &lazy_adam_rows, "Adam's update of the given rows of a parameter and its moments, in place");
}
