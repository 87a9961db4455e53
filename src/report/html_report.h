// report.html: one self-contained page (no network access when opened) with the results table
// and, per sequence, plots of the estimate against ground truth, the error along the path,
// frames/s and keyframes over time. The plots are drawn by Chart.js (Debian's libjs-chart.js),
// read at report time and inlined into the page.
// Concurrency: free functions; reads the sequence folders, writes one file.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "report/results.h"

namespace flatslam {

// A sequence of the report: its row of the results table and its output folder, which holds
// what `flatslam run --out` writes: trajectory.tum, stats.csv, and groundtruth.tum when the
// dataset has ground truth.
struct ReportSequence {
  SequenceResult result;
  std::filesystem::path dir;
};

// Writes the report atomically. A sequence whose folder lacks a file gets the plots it can make
// and a line saying what is missing; monocular estimates are aligned by Sim(3), others by
// SE(3). Throws flatslam::Error naming the Chart.js file when it cannot be read.
void WriteHtmlReport(const std::filesystem::path& html, const std::string& title,
                     const std::vector<ReportSequence>& sequences);

}  // namespace flatslam
