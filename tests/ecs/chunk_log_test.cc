#include "ecs/chunk_log.h"

#include <cstdint>
#include <vector>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

struct Record {
  uint64_t index = 0;
  double value = 0;
};

using SmallLog = ChunkLog<Record, 4>;

std::vector<Record> Collect(const SmallLog::View& view) {
  std::vector<Record> out;
  view.ForEach([&](const Record& r) { out.push_back(r); });
  return out;
}

void ExpectSequence(const std::vector<Record>& records, size_t count) {
  ASSERT_EQ(records.size(), count);
  for (size_t i = 0; i < count; ++i) {
    EXPECT_EQ(records[i].index, i);
    EXPECT_EQ(records[i].value, 0.5 * static_cast<double>(i));
  }
}

// A spilling log keeps its last two chunks in memory and reads the rest back from its file,
// element by element and in order, exactly as written.
TEST(ChunkLog, SpillsOlderChunksAndReadsThemBack) {
  SmallLog log;
  log.SpillToFile();
  for (uint64_t i = 0; i < 8; ++i) log.push_back({i, 0.5 * static_cast<double>(i)});
  EXPECT_EQ(log.spilled_chunks(), 0u);  // two chunks: nothing to spill yet
  for (uint64_t i = 8; i < 50; ++i) log.push_back({i, 0.5 * static_cast<double>(i)});
  // 50 records = 13 chunks; the newest (partial) one and the full one before it stay in memory.
  EXPECT_EQ(log.spilled_chunks(), 11u);
  for (size_t i = 0; i < log.size(); ++i) EXPECT_EQ(log[i].index, i);
  EXPECT_EQ(log.back().index, 49u);
  std::vector<Record> all;
  log.ForEach([&](const Record& r) { all.push_back(r); });
  ExpectSequence(all, 50);
}

// A view taken between appends reads exactly the elements of its time, while the writer appends
// and spills the chunks the view still holds in memory.
TEST(ChunkLog, AViewKeepsItsElementsWhileTheLogSpillsOn) {
  SmallLog log;
  log.SpillToFile();
  for (uint64_t i = 0; i < 30; ++i) log.push_back({i, 0.5 * static_cast<double>(i)});
  SmallLog::View view;
  log.TakeView(&view);
  for (uint64_t i = 30; i < 200; ++i) log.push_back({i, 0.5 * static_cast<double>(i)});
  EXPECT_GT(log.spilled_chunks(), 40u);
  ExpectSequence(Collect(view), 30);
  // Part of a view: from the middle of a spilled chunk into the ones in memory.
  std::vector<Record> part;
  log.TakeView(&view);
  view.ForEach(45, 199, [&](const Record& r) { part.push_back(r); });
  ASSERT_EQ(part.size(), 154u);
  EXPECT_EQ(part.front().index, 45u);
  EXPECT_EQ(part.back().index, 198u);
}

// Without SpillToFile everything stays in memory.
TEST(ChunkLog, WithoutSpillingNothingLeavesMemory) {
  SmallLog log;
  for (uint64_t i = 0; i < 40; ++i) log.push_back({i, 0.5 * static_cast<double>(i)});
  EXPECT_EQ(log.spilled_chunks(), 0u);
  SmallLog::View view;
  log.TakeView(&view);
  ExpectSequence(Collect(view), 40);
}

}  // namespace
}  // namespace flatslam
