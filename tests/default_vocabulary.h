// The shipped bag-of-words vocabulary for tests that run place recognition, loaded once per test
// process.
#pragma once

#include "config/options.h"
#include "place/vocabulary.h"

namespace flatslam::testing {

inline const Vocabulary& DefaultVocabulary() {
  static const Vocabulary vocabulary = Vocabulary::Load(DefaultVocabularyPath());
  return vocabulary;
}

// Default options with the shipped vocabulary (relocalization and loop closing on).
inline SlamOptions OptionsWithDefaultVocabulary() {
  SlamOptions options;
  options.vocabulary = &DefaultVocabulary();
  return options;
}

}  // namespace flatslam::testing
