#include "args.h"

#include <charconv>
#include <cmath>
#include <stdexcept>

namespace flatslam::app {

Args::Args(const std::vector<std::string>& argv, const std::set<std::string>& flags,
           const std::set<std::string>& switches, const std::set<std::string>& lists) {
  auto store = [&](const std::string& name, const std::string& value) {
    auto [it, fresh] = values_.emplace(name, value);
    if (fresh || it->second == value) return;
    if (!lists.count(name))
      throw UsageError{"option --" + name + " given twice ('" + it->second + "' and '" + value + "'): give it once"};
    it->second += "," + value;
  };
  for (size_t i = 0; i < argv.size(); ++i) {
    const std::string& a = argv[i];
    if (a == "--help" || a == "-h") {
      help_ = true;
      continue;
    }
    if (a.size() > 2 && a.rfind("--", 0) == 0) {
      std::string name = a.substr(2);
      std::optional<std::string> inline_value;
      if (auto eq = name.find('='); eq != std::string::npos) {
        inline_value = name.substr(eq + 1);
        name = name.substr(0, eq);
      }
      if (switches.count(name)) {
        if (inline_value) throw UsageError{"option --" + name + " takes no value"};
        values_[name] = "1";
      } else if (flags.count(name)) {
        if (inline_value) {
          store(name, *inline_value);
        } else {
          if (i + 1 >= argv.size()) throw UsageError{"option --" + name + " needs a value"};
          store(name, argv[++i]);
        }
      } else {
        throw UsageError{"unknown option --" + name};
      }
      continue;
    }
    positional_.push_back(a);
  }
}

std::optional<std::string> Args::get(const std::string& name) const {
  auto it = values_.find(name);
  if (it == values_.end()) return std::nullopt;
  return it->second;
}

std::string Args::get_or(const std::string& name, const std::string& fallback) const {
  return get(name).value_or(fallback);
}

double Args::get_double(const std::string& name, double fallback) const {
  auto v = get(name);
  if (!v) return fallback;
  try {
    size_t used = 0;
    const double d = std::stod(*v, &used);
    if (used != v->size() || !std::isfinite(d)) throw std::invalid_argument(*v);
    return d;
  } catch (const std::exception&) {
    throw UsageError{"option --" + name + ": '" + *v + "' is not a number"};
  }
}

int64_t Args::get_int(const std::string& name, int64_t fallback) const {
  auto v = get(name);
  if (!v) return fallback;
  int64_t out = 0;
  auto [ptr, ec] = std::from_chars(v->data(), v->data() + v->size(), out);
  if (ec != std::errc() || ptr != v->data() + v->size())
    throw UsageError{"option --" + name + ": '" + *v + "' is not an integer"};
  return out;
}

}  // namespace flatslam::app
