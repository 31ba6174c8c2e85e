#include "server/core/metrics.hpp"

#include <sstream>

namespace stereomap::core {

std::string Metrics::labelText(const Labels& labels) {
  if (labels.empty()) return "";
  std::string text = "{";
  for (size_t i = 0; i < labels.size(); ++i) {
    if (i > 0) text += ",";
    text += labels[i].first + "=\"";
    for (char c : labels[i].second) {  // escape per the exposition format
      if (c == '\\' || c == '"' || c == '\n') text += '\\';
      text += c == '\n' ? 'n' : c;
    }
    text += "\"";
  }
  return text + "}";
}

void Metrics::describe(const std::string& name, const std::string& type, const std::string& help) {
  std::lock_guard lock(mutex_);
  auto& family = families_[name];
  family.type = type;
  family.help = help;
}

void Metrics::add(const std::string& name, const Labels& labels, double value) {
  std::lock_guard lock(mutex_);
  families_[name].series[labelText(labels)] += value;
}

void Metrics::set(const std::string& name, const Labels& labels, double value) {
  std::lock_guard lock(mutex_);
  families_[name].series[labelText(labels)] = value;
}

double Metrics::get(const std::string& name, const Labels& labels) const {
  std::lock_guard lock(mutex_);
  const auto family = families_.find(name);
  if (family == families_.end()) return 0;
  const auto series = family->second.series.find(labelText(labels));
  return series == family->second.series.end() ? 0 : series->second;
}

void Metrics::removeSeries(const std::string& label, const std::string& value) {
  const std::string one = labelText({{label, value}});  // {label="value"}
  const std::string pair = one.substr(1, one.size() - 2);
  std::lock_guard lock(mutex_);
  for (auto& [name, family] : families_) {
    std::erase_if(family.series, [&](const auto& series) {
      const std::string& text = series.first;
      for (size_t at = text.find(pair); at != std::string::npos; at = text.find(pair, at + 1)) {
        const char before = text[at - 1], after = text[at + pair.size()];
        if ((before == '{' || before == ',') && (after == ',' || after == '}')) return true;
      }
      return false;
    });
  }
}

std::string Metrics::render() const {
  std::lock_guard lock(mutex_);
  std::ostringstream out;
  out.precision(15);  // byte counts exact (the default 6 digits printed 3.81235e+07)
  for (const auto& [name, family] : families_) {
    if (!family.help.empty()) out << "# HELP " << name << " " << family.help << "\n";
    if (!family.type.empty()) out << "# TYPE " << name << " " << family.type << "\n";
    for (const auto& [labels, value] : family.series) out << name << labels << " " << value << "\n";
  }
  return out.str();
}

}  // namespace stereomap::core
