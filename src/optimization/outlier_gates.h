// The outlier gates and robust-kernel widths that pose optimization and bundle adjustment share:
// chi-square gates at 95% for 2 (monocular) and 3 (stereo) degrees of freedom, and the Huber
// delta on the whitened residual at their square roots, as ORB-SLAM2 uses in both.
// X(type, name, default, requirement, description) entries (core/option_fields.h) for the
// options lists that include them.
// Concurrency: a macro; nothing at run time.
#pragma once

#include <cmath>

#define FLATSLAM_OUTLIER_GATE_OPTIONS(X)                                                                    \
  X(double, chi2_mono, 5.991, chi2_mono > 0, "outlier gate, 2 DoF at 95%")                                  \
  X(double, chi2_stereo, 7.815, chi2_stereo > 0, "outlier gate, 3 DoF at 95%")                              \
  X(double, huber_mono, std::sqrt(5.991), huber_mono > 0, "Huber delta on the whitened monocular residual") \
  X(double, huber_stereo, std::sqrt(7.815), huber_stereo > 0, "Huber delta on the whitened stereo residual")
