// A column of values that is written once and then only read (a keyframe's keypoints and
// descriptors), shared between copies: copying a SharedColumn copies a pointer, so a copy of
// the map (a checkpoint's, local mapping's) holds no second copy of what never changes. Writing
// replaces the whole column (assignment, assign, resize) or, through mutable_data(), copies it
// first when another copy shares it.
// Concurrency: the values are immutable while shared; copies may be read on many threads.
#pragma once

#include <cstddef>
#include <memory>
#include <span>
#include <vector>

namespace flatslam {

template <class T>
class SharedColumn {
 public:
  SharedColumn() = default;
  SharedColumn(std::vector<T> values) : values_(Make(std::move(values))) {}  // NOLINT: a column is its values
  SharedColumn& operator=(std::vector<T> values) {
    values_ = Make(std::move(values));
    return *this;
  }
  template <class It>
  void assign(It first, It last) {
    values_ = Make(std::vector<T>(first, last));
  }
  void resize(size_t n, const T& value = T()) {
    std::vector<T> values = vector();
    values.resize(n, value);
    values_ = Make(std::move(values));
  }
  void clear() { values_.reset(); }

  [[nodiscard]] size_t size() const { return values_ ? values_->size() : 0; }
  [[nodiscard]] bool empty() const { return size() == 0; }
  [[nodiscard]] const T& operator[](size_t i) const { return (*values_)[i]; }
  [[nodiscard]] const T* data() const { return values_ ? values_->data() : nullptr; }
  [[nodiscard]] const T* begin() const { return data(); }
  [[nodiscard]] const T* end() const { return data() + size(); }
  [[nodiscard]] const std::vector<T>& vector() const { return values_ ? *values_ : Empty(); }
  operator std::span<const T>() const { return {data(), size()}; }  // NOLINT: read as a span anywhere

  // The values to write in place; copied first when another column shares them.
  [[nodiscard]] T* mutable_data() {
    if (!values_) return nullptr;
    if (values_.use_count() > 1) values_ = Make(std::vector<T>(*values_));
    return const_cast<T*>(values_->data());
  }
  // Equal values (shared or not).
  [[nodiscard]] bool operator==(const SharedColumn& other) const { return vector() == other.vector(); }
  // Whether two columns share their values (tests).
  [[nodiscard]] bool shares_with(const SharedColumn& other) const { return values_ && values_ == other.values_; }

 private:
  static std::shared_ptr<const std::vector<T>> Make(std::vector<T>&& values) {
    return std::make_shared<const std::vector<T>>(std::move(values));
  }
  static const std::vector<T>& Empty() {
    static const std::vector<T> empty;
    return empty;
  }
  std::shared_ptr<const std::vector<T>> values_;
};

}  // namespace flatslam
