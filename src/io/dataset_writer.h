// Writes any Dataset (typically a synthetic scene) to disk in the KITTI odometry, TUM RGB-D
// or EuRoC ASL layout, so that the matching reader reads back the same frames and poses.
// Concurrency: WriteDataset renders and encodes frames in parallel (dataset.read() must be
// thread-safe, as the Dataset contract says); call it from one thread.
#pragma once

#include <cstddef>
#include <filesystem>
#include <functional>
#include <string>

#include "io/dataset.h"

namespace flatslam {

enum class DatasetFormat { kKitti, kTum, kEuroc };

// "kitti", "tum", "euroc"; throws flatslam::Error otherwise.
[[nodiscard]] DatasetFormat ParseDatasetFormat(const std::string& name);

struct DatasetWriteResult {
  size_t frames = 0;
  // What to pass to OpenDataset() to read it back (e.g. DIR/sequences/00 for KITTI).
  std::filesystem::path dataset_path;
};

// Writes all frames, calibration and ground truth under dir, which must not exist or be
// empty. Everything is written to a sibling temporary folder first and renamed into place
// at the end, so a failure leaves no half-written dataset behind. KITTI and EuRoC take mono
// or stereo data, TUM takes RGB-D (or mono); other combinations are an error.
// progress(done, total) is called from the calling thread.
DatasetWriteResult WriteDataset(const Dataset& dataset, const std::filesystem::path& dir, DatasetFormat format,
                                const std::function<void(size_t, size_t)>& progress = {});

}  // namespace flatslam
